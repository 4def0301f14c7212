//! The MEB slave front end: one well-formed frame in, the reply (if any) out,
//! with the checks in the order `docs/protocols/meb.md` gives them.

use protocols::meb::{MebAccess, MebBlock, MebRepr, MebWordType, MebWords};

use super::image::{self, Refusal, RegisterImage, WriteSet};
use super::meb_map::MebMap;

/// Words the default map holds in a block.
fn block_size(block: MebBlock, word_type: MebWordType) -> usize {
    use MebBlock::*;
    use MebWordType::*;
    match (block, word_type) {
        (Inputs, Analog) => image::EA_WORDS,
        (Inputs, Digital) => image::ED_WORDS,
        (Outputs, Analog) => image::SA_WORDS,
        (Outputs, Digital) => image::SD_WORDS,
        (Variables, Analog) => image::VA_WORDS,
        (Variables, Digital) => image::VD_WORDS,
        (Flags, Analog) => image::FA_WORDS,
        (Flags, Digital) => image::FD_WORDS,
    }
}

/// The word at `index` of a readable block.
fn read_word(image: &RegisterImage, block: MebBlock, word_type: MebWordType, index: usize) -> u16 {
    use MebBlock::*;
    use MebWordType::*;
    match (block, word_type, index) {
        (Inputs, Analog, i) => image.inputs.get(i).copied().unwrap_or(0),
        (Inputs, Digital, 0) => image.hall,
        (Flags, Analog, 0) => image.soc,
        (Flags, Analog, 1) => image.errs,
        (Flags, Digital, 0) => image.status,
        _ => 0,
    }
}

/// Puts a word written at `index` of a writable block into `set`.
fn write_word(
    set: &mut WriteSet,
    block: MebBlock,
    word_type: MebWordType,
    index: usize,
    word: u16,
) {
    use MebBlock::*;
    use MebWordType::*;
    let slot = match (block, word_type, index) {
        (Outputs, Analog, 0) => &mut set.vel,
        (Outputs, Digital, 0) => &mut set.sd0,
        (Outputs, Digital, 1) => &mut set.sd1,
        (Variables, Analog, 0) => &mut set.ldr_threshold,
        (Variables, Analog, 1) => &mut set.rpm_window_ms,
        (Variables, Digital, 0) => &mut set.ldr_adaptive,
        // The address check keeps every index inside the block.
        _ => return,
    };
    *slot = Some(word);
}

/// Serves one well-formed frame heard on the bus; returns the reply to send.
///
/// Silent on reply-shaped frames, on other slaves' ids, on every broadcast
/// (broadcast writes that pass every check are stored) and on frames whose
/// reply would be an error to a broadcast.
pub fn serve(image: &mut RegisterImage, own_id: u8, request: &MebRepr) -> Option<MebRepr> {
    serve_mapped(image, own_id, request, None)
}

/// [`serve`] with the signals where `map` puts them (`None`: the default map).
pub fn serve_mapped(
    image: &mut RegisterImage,
    own_id: u8,
    request: &MebRepr,
    map: Option<&MebMap>,
) -> Option<MebRepr> {
    if request.shape().is_reply() {
        return None;
    }
    let broadcast = request.is_broadcast();
    if request.id != own_id && !broadcast {
        return None;
    }
    let answer = execute(image, request, broadcast, map);
    if broadcast {
        return None;
    }
    Some(match answer {
        Ok(reply) => reply,
        Err(refusal) => MebRepr::error_reply(own_id, request.addr, refusal.meb()),
    })
}

/// The reply when every request is refused with `refusal` (an injected
/// fault, a read-only client): the `ER` reply to a request for this slave;
/// silence to replies, to other slaves' requests and to broadcasts. Nothing
/// is stored.
pub fn refuse(own_id: u8, request: &MebRepr, refusal: Refusal) -> Option<MebRepr> {
    if request.shape().is_reply() || request.is_broadcast() || request.id != own_id {
        return None;
    }
    Some(MebRepr::error_reply(own_id, request.addr, refusal.meb()))
}

/// The checks and the action: command (01), CNT 0 (03), address range (02),
/// values (03), whether it may be applied now (04).
fn execute(
    image: &mut RegisterImage,
    request: &MebRepr,
    broadcast: bool,
    map: Option<&MebMap>,
) -> Result<MebRepr, Refusal> {
    let (block, word_type) = request.cmd.block().ok_or(Refusal::IllegalCommand)?;
    let size = match map {
        Some(map) => map.block_len(block, word_type),
        None => block_size(block, word_type),
    };
    if size == 0 {
        return Err(Refusal::IllegalCommand);
    }
    let access = block.access();
    if broadcast && access == MebAccess::Read {
        // Neither executed nor answered: the caller drops whatever comes back.
        return Err(Refusal::IllegalCommand);
    }
    if request.cnt == 0 {
        return Err(Refusal::IllegalData);
    }
    let first = usize::from(request.addr);
    let count = usize::from(request.cnt);
    if first + count > size {
        return Err(Refusal::IllegalAddress);
    }
    if let Some(map) = map {
        return execute_mapped(image, request, map, block, word_type);
    }
    match access {
        MebAccess::Read => {
            let mut data = MebWords::new();
            for index in first..first + count {
                // At most 99 words: CNT has two digits.
                let _ = data.push(read_word(image, block, word_type, index));
            }
            Ok(MebRepr { data, ..*request })
        }
        MebAccess::Write => {
            let mut set = WriteSet::default();
            for (index, word) in (first..).zip(request.data.iter()) {
                write_word(&mut set, block, word_type, index, *word);
            }
            image.store(&set)?;
            Ok(request.acknowledgement())
        }
    }
}

/// The read or write of a request that passed the checks, through `map`:
/// each user address is translated to the default map's word (or, for SD,
/// bit by bit). An address the map leaves empty is refused (02).
fn execute_mapped(
    image: &mut RegisterImage,
    request: &MebRepr,
    map: &MebMap,
    block: MebBlock,
    word_type: MebWordType,
) -> Result<MebRepr, Refusal> {
    let first = usize::from(request.addr);
    let count = usize::from(request.cnt);
    match block.access() {
        MebAccess::Read => {
            let mut data = MebWords::new();
            for address in first..first + count {
                let index = map
                    .word(block, word_type, address)
                    .ok_or(Refusal::IllegalAddress)?;
                let _ = data.push(read_word(image, block, word_type, index));
            }
            Ok(MebRepr { data, ..*request })
        }
        MebAccess::Write => {
            let mut set = WriteSet::default();
            for (address, &word) in (first..).zip(request.data.iter()) {
                if let Some(index) = map.word(block, word_type, address) {
                    write_word(&mut set, block, word_type, index, word);
                    continue;
                }
                let mut any = false;
                for (bit, home_word, home_bit) in map.bits(block, word_type, address) {
                    any = true;
                    let (slot, stored) = match home_word {
                        0 => (&mut set.sd0, image.stored.sd0),
                        _ => (&mut set.sd1, image.stored.sd1),
                    };
                    let current = slot.unwrap_or(stored);
                    let on = word & (1 << bit) != 0;
                    *slot = Some(if on {
                        current | 1 << home_bit
                    } else {
                        current & !(1 << home_bit)
                    });
                }
                if !any {
                    return Err(Refusal::IllegalAddress);
                }
            }
            image.store(&set)?;
            Ok(request.acknowledgement())
        }
    }
}
