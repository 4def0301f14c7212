//! Where each signal sits in MEB's blocks: the I/O map the lab's tool lets
//! one configure (the M3CVME paper, Fig. 8: type, address, tag). The default is the
//! map of `docs/protocols/meb.md`; a front end given another one answers at the
//! addresses it says, with the same checks and the same image.

use protocols::meb::{MebBlock, MebWordType};

/// A signal of the EV module and its place in the default map.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Tag {
    pub name: &'static str,
    pub block: MebBlock,
    pub word_type: MebWordType,
    /// Word address in the default map.
    pub index: u8,
    /// For a digital output bit (EN, BRK, …): its bit in that word.
    pub bit: Option<u8>,
}

const fn tag(
    name: &'static str,
    block: MebBlock,
    wt: MebWordType,
    index: u8,
    bit: Option<u8>,
) -> Tag {
    Tag {
        name,
        block,
        word_type: wt,
        index,
        bit,
    }
}

use MebBlock::{Flags, Inputs, Outputs, Variables};
use MebWordType::{Analog, Digital};

/// Every signal the map can place.
pub const TAGS: [Tag; 18] = [
    tag("V2", Inputs, Analog, 0, None),
    tag("I", Inputs, Analog, 1, None),
    tag("V1", Inputs, Analog, 2, None),
    tag("RPM_M", Inputs, Analog, 3, None),
    tag("RPM_L", Inputs, Analog, 4, None),
    tag("LDR", Inputs, Analog, 5, None),
    tag("HALL", Inputs, Digital, 0, None),
    tag("VEL", Outputs, Analog, 0, None),
    tag("EN", Outputs, Digital, 0, Some(0)),
    tag("BRK", Outputs, Digital, 0, Some(1)),
    tag("PRO", Outputs, Digital, 0, Some(2)),
    tag("DES", Outputs, Digital, 0, Some(3)),
    tag("FR", Outputs, Digital, 0, Some(4)),
    tag("CHG", Outputs, Digital, 1, Some(0)),
    tag("LDR_TH", Variables, Analog, 0, None),
    tag("RPM_WIN", Variables, Analog, 1, None),
    tag("LDR_ADAPT", Variables, Digital, 0, None),
    tag("SOC", Flags, Analog, 0, None),
];
/// The flags not in [`TAGS`] keep their place: ERRS (FA 1) and STATUS (FD 0)
/// are the firmware's own.
const FIXED: [Tag; 2] = [
    tag("ERRS", Flags, Analog, 1, None),
    tag("STATUS", Flags, Digital, 0, None),
];

/// A signal's place in the default map's order: [`TAGS`], then [`FIXED`].
fn order(tag: &Tag) -> usize {
    TAGS.iter()
        .chain(FIXED.iter())
        .position(|t| t == tag)
        .unwrap_or(usize::MAX)
}

/// Highest word address a map may use (CNT and ADDR are two digits).
pub const MAX_ADDRESS: u8 = 98;

/// Why a placement is refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MapError {
    #[error(
        "unknown signal `{0}` (known: V2, I, V1, RPM_M, RPM_L, LDR, HALL, VEL, EN, BRK, PRO, DES, FR, CHG, LDR_TH, RPM_WIN, LDR_ADAPT, SOC)"
    )]
    UnknownTag(String),
    #[error("`{tag}` belongs in {expected}, not {given}")]
    WrongBlock {
        tag: String,
        expected: &'static str,
        given: String,
    },
    #[error("`{0}` is a bit of an SD word: give it as \"WORD.BIT\", e.g. \"0.3\"")]
    NeedsBit(String),
    #[error("`{0}` is a whole word: give its address as a number")]
    NoBit(String),
    #[error("address {0} is past {MAX_ADDRESS}")]
    AddressTooHigh(u16),
    #[error("bit {0} is past 15")]
    BitTooHigh(u16),
    #[error("`{tag}` would share {place} with `{other}`")]
    Taken {
        tag: String,
        place: String,
        other: &'static str,
    },
}

/// The block's two-letter prefix (`EA`, `SD`, …).
pub fn block_name(block: MebBlock, word_type: MebWordType) -> &'static str {
    match (block, word_type) {
        (Inputs, Analog) => "EA",
        (Inputs, Digital) => "ED",
        (Outputs, Analog) => "SA",
        (Outputs, Digital) => "SD",
        (Variables, Analog) => "VA",
        (Variables, Digital) => "VD",
        (Flags, Analog) => "FA",
        (Flags, Digital) => "FD",
    }
}

/// One placement: the tag at a user address (and bit).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Placement {
    tag: Tag,
    address: u8,
    bit: Option<u8>,
}

/// An I/O map. [`MebMap::default`] is `docs/protocols/meb.md`'s.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MebMap {
    placed: Vec<Placement>,
}

impl Default for MebMap {
    fn default() -> Self {
        let placed = TAGS
            .iter()
            .chain(FIXED.iter())
            .map(|&tag| Placement {
                tag,
                address: tag.index,
                bit: tag.bit,
            })
            .collect();
        MebMap { placed }
    }
}

impl MebMap {
    /// Whether this is the default map.
    pub fn is_default(&self) -> bool {
        *self == MebMap::default()
    }

    /// Removes every signal of block `name` (`EA`, `SD`, …) but the fixed
    /// flags, before the block is placed anew.
    pub fn clear_block(&mut self, name: &str) {
        self.placed
            .retain(|p| block_name(p.tag.block, p.tag.word_type) != name || FIXED.contains(&p.tag));
    }

    /// Puts signal `name` at `address` (and `bit`) of block `block`.
    pub fn place(
        &mut self,
        block: &str,
        name: &str,
        address: u16,
        bit: Option<u16>,
    ) -> Result<(), MapError> {
        let upper = name.to_ascii_uppercase();
        let tag = *TAGS
            .iter()
            .find(|t| t.name == upper)
            .ok_or_else(|| MapError::UnknownTag(name.into()))?;
        let expected = block_name(tag.block, tag.word_type);
        if !expected.eq_ignore_ascii_case(block) {
            return Err(MapError::WrongBlock {
                tag: upper,
                expected,
                given: block.into(),
            });
        }
        match (tag.bit, bit) {
            (Some(_), None) => return Err(MapError::NeedsBit(upper)),
            (None, Some(_)) => return Err(MapError::NoBit(upper)),
            _ => {}
        }
        let address = u8::try_from(address)
            .ok()
            .filter(|a| *a <= MAX_ADDRESS)
            .ok_or(MapError::AddressTooHigh(address))?;
        let bit = match bit {
            Some(b) if b > 15 => return Err(MapError::BitTooHigh(b)),
            Some(b) => Some(b as u8),
            None => None,
        };
        self.placed.retain(|p| p.tag != tag);
        if let Some(other) = self.placed.iter().find(|p| {
            p.tag.block == tag.block
                && p.tag.word_type == tag.word_type
                && p.address == address
                && (p.bit.is_none() || bit.is_none() || p.bit == bit)
        }) {
            let place = match bit {
                Some(b) => format!("{expected} {address} bit {b}"),
                None => format!("{expected} {address}"),
            };
            return Err(MapError::Taken {
                tag: upper,
                place,
                other: other.tag.name,
            });
        }
        self.placed.push(Placement { tag, address, bit });
        // In the signals' own order, whatever the order they were placed
        // in: two maps that place alike compare equal.
        self.placed.sort_by_key(|p| order(&p.tag));
        Ok(())
    }

    /// Every signal the user can place, in the order of [`TAGS`]: its
    /// block (`EA`, `SD`, …), name, address and bit.
    pub fn placements(
        &self,
    ) -> impl Iterator<Item = (&'static str, &'static str, u8, Option<u8>)> + '_ {
        self.placed
            .iter()
            .filter(|p| !FIXED.contains(&p.tag))
            .map(|p| {
                (
                    block_name(p.tag.block, p.tag.word_type),
                    p.tag.name,
                    p.address,
                    p.bit,
                )
            })
    }

    /// Words the block holds: one past its highest address in use.
    pub fn block_len(&self, block: MebBlock, word_type: MebWordType) -> usize {
        self.in_block(block, word_type)
            .map(|p| usize::from(p.address) + 1)
            .max()
            .unwrap_or(0)
    }

    fn in_block(
        &self,
        block: MebBlock,
        word_type: MebWordType,
    ) -> impl Iterator<Item = &Placement> {
        self.placed
            .iter()
            .filter(move |p| p.tag.block == block && p.tag.word_type == word_type)
    }

    /// The default-map index of the whole word at `address`, if any.
    pub fn word(&self, block: MebBlock, word_type: MebWordType, address: usize) -> Option<usize> {
        self.in_block(block, word_type)
            .find(|p| usize::from(p.address) == address && p.bit.is_none())
            .map(|p| usize::from(p.tag.index))
    }

    /// The bits placed in word `address`: (user bit, default word, default bit).
    pub fn bits(
        &self,
        block: MebBlock,
        word_type: MebWordType,
        address: usize,
    ) -> impl Iterator<Item = (u8, usize, u8)> + '_ {
        self.in_block(block, word_type).filter_map(move |p| {
            let (bit, home) = (p.bit?, p.tag.bit?);
            (usize::from(p.address) == address).then_some((bit, usize::from(p.tag.index), home))
        })
    }
}
