//! Where the supervisor finds a slave's signals on MEB: the slave's I/O map
//! (the M3CVME tool's table of type, address and tag) turned into the reads
//! and writes of a poll cycle. Everything is worked out once, from the map,
//! so a cycle only looks numbers up.
//!
//! A mapped slave refuses (`ER 02`) a read or write that touches an address
//! its map leaves empty, so the supervisor reads and writes each block in
//! spans of neighbouring addresses: the default map gives one span per block
//! (`EA 00 06`, `SD 00 02`), as before.

use crate::firmware::{MebMap, TAGS, block_name};
use protocols::meb::{MebBlock, MebCmd, MebWordType, MebWords};

/// The analog inputs read every cycle: V2, I, V1, RPM_M, RPM_L, LDR.
pub(crate) const INPUT_WORDS: usize = 6;

/// The switches as the lab's I/O list names them, with their place in the
/// default map (`SD` word, bit): `SD 00` bits 0–4, `SD 01` bit 0.
pub const SWITCHES: [(&str, u8, u8); 6] = [
    ("EN", 0, 0),
    ("BRK", 0, 1),
    ("PRO", 0, 2),
    ("DES", 0, 3),
    ("FR", 0, 4),
    ("CHG", 1, 0),
];

/// Where ERRS sits in every map (the firmware's own).
const ERRS_ADDRESS: u8 = 1;

/// Runs of neighbouring addresses, lowest first: `(first, count)`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct Spans {
    spans: [(u8, u8); INPUT_WORDS],
    len: u8,
}

impl Spans {
    fn of(addresses: impl Iterator<Item = u8>) -> Self {
        let mut sorted = [u8::MAX; INPUT_WORDS];
        let mut n = 0;
        for address in addresses {
            if n < INPUT_WORDS && !sorted[..n].contains(&address) {
                sorted[n] = address;
                n += 1;
            }
        }
        sorted[..n].sort_unstable();
        let mut spans = Spans::default();
        for &address in &sorted[..n] {
            match spans.spans[..usize::from(spans.len)].last_mut() {
                Some((first, count)) if *first + *count == address => *count += 1,
                _ => {
                    spans.spans[usize::from(spans.len)] = (address, 1);
                    spans.len += 1;
                }
            }
        }
        spans
    }

    pub(crate) fn get(&self, part: u8) -> Option<(u8, u8)> {
        self.spans[..usize::from(self.len)]
            .get(usize::from(part))
            .copied()
    }

    pub(crate) fn is_last(&self, part: u8) -> bool {
        part + 1 >= self.len
    }
}

/// A signal the supervisor cannot do without is missing from the map.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LayoutError {
    #[error("the I/O map places no {0}, which the supervisor {1}")]
    Missing(&'static str, &'static str),
}

/// Why a client's write cannot be put into the slave's map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum TranslateError {
    /// The written words have no place in the slave's map.
    #[error("the slave's I/O map has no place for these words")]
    NotInMap,
    /// The slave's map puts them apart: one write cannot carry them.
    #[error("the slave's I/O map puts these words apart: write them one at a time")]
    Scattered,
}

/// The reads and writes of a poll cycle for a slave with a given I/O map.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MebLayout {
    /// `EA` address of each input, in the default order (V2, I, V1, RPM_M, RPM_L, LDR).
    inputs: [Option<u8>; INPUT_WORDS],
    input_spans: Spans,
    vel: Option<u8>,
    /// `SD` word and bit of each switch, in [`SWITCHES`]' order.
    switches: [Option<(u8, u8)>; 6],
    sd_spans: Spans,
    hall: Option<u8>,
    soc: Option<u8>,
    map: MebMap,
}

impl Default for MebLayout {
    fn default() -> Self {
        Self::from_map(&MebMap::default())
    }
}

impl MebLayout {
    /// The layout of a slave answering through `map`.
    pub fn from_map(map: &MebMap) -> Self {
        let find = |block: &str, name: &str| {
            map.placements()
                .find(|(b, n, _, _)| *b == block && *n == name)
                .map(|(_, _, address, bit)| (address, bit))
        };
        let mut inputs = [None; INPUT_WORDS];
        for tag in TAGS
            .iter()
            .filter(|t| t.block == MebBlock::Inputs && t.word_type == MebWordType::Analog)
        {
            if let Some(slot) = inputs.get_mut(usize::from(tag.index)) {
                *slot = find("EA", tag.name).map(|(address, _)| address);
            }
        }
        let mut switches = [None; 6];
        for (slot, (name, _, _)) in switches.iter_mut().zip(SWITCHES) {
            *slot = find("SD", name).and_then(|(word, bit)| Some((word, bit?)));
        }
        MebLayout {
            inputs,
            input_spans: Spans::of(inputs.iter().flatten().copied()),
            vel: find("SA", "VEL").map(|(a, _)| a),
            switches,
            sd_spans: Spans::of(switches.iter().flatten().map(|(word, _)| *word)),
            hall: find("ED", "HALL").map(|(a, _)| a),
            soc: find("FA", "SOC").map(|(a, _)| a),
            map: map.clone(),
        }
    }

    /// `EA` address of input `i` (V2, I, V1, RPM_M, RPM_L, LDR), if the
    /// map places it.
    pub fn input_address(&self, i: usize) -> Option<u8> {
        self.inputs.get(i).copied().flatten()
    }

    /// `SD` word and bit of switch `i` of [`SWITCHES`], if the map places it.
    pub fn switch_place(&self, i: usize) -> Option<(u8, u8)> {
        self.switches.get(i).copied().flatten()
    }

    /// `SA` address of VEL, if the map places it.
    pub fn vel_address(&self) -> Option<u8> {
        self.vel
    }

    /// `FA` address of SOC, if the map places it.
    pub fn soc_address(&self) -> Option<u8> {
        self.soc
    }

    /// Whether this is the protocol page's map.
    pub fn is_default(&self) -> bool {
        self.map.is_default()
    }

    /// Refuses a map without the signal the loop measures (`input`, in the
    /// default order) or without VEL.
    pub fn check(&self, input: usize, name: &'static str) -> Result<(), LayoutError> {
        if self.inputs.get(input).copied().flatten().is_none() {
            return Err(LayoutError::Missing(name, "measures the speed with"));
        }
        if self.vel.is_none() {
            return Err(LayoutError::Missing("VEL", "writes the loop's output to"));
        }
        Ok(())
    }

    pub(crate) fn input_spans(&self) -> &Spans {
        &self.input_spans
    }

    pub(crate) fn sd_spans(&self) -> &Spans {
        &self.sd_spans
    }

    pub(crate) fn vel(&self) -> u8 {
        self.vel.unwrap_or(0)
    }

    /// Puts the words of an `EA first..` read where the inputs go.
    pub(crate) fn place_inputs(&self, first: u8, words: &[u16], into: &mut [u16; INPUT_WORDS]) {
        for (slot, address) in into.iter_mut().zip(self.inputs) {
            if let Some(word) = address
                .and_then(|a| a.checked_sub(first))
                .and_then(|offset| words.get(usize::from(offset)))
            {
                *slot = *word;
            }
        }
    }

    /// The slave's `SD` word `word` with the switches set as the default
    /// map's words `sd` say.
    pub(crate) fn sd_word(&self, word: u8, sd: [u16; 2]) -> u16 {
        let mut out = 0;
        for (place, (_, home_word, home_bit)) in self.switches.iter().zip(SWITCHES) {
            if let Some((w, bit)) = *place
                && w == word
                && sd[usize::from(home_word)] & (1 << home_bit) != 0
            {
                out |= 1 << bit;
            }
        }
        out
    }

    /// `ED` of the hall code, if the map places it.
    pub fn hall(&self) -> Option<u8> {
        self.hall
    }

    /// The `FA` read of a status round: SOC with ERRS when they neighbour,
    /// `(first, count, soc_offset)`.
    pub(crate) fn flags_read(&self) -> Option<(u8, u8, Option<u8>)> {
        match self.soc {
            Some(0) => Some((0, 2, Some(0))),
            Some(2) => Some((ERRS_ADDRESS, 2, Some(1))),
            Some(soc) => Some((soc, 1, Some(0))),
            None => None,
        }
    }

    /// Whether ERRS needs a read of its own (the flags read leaves it out).
    pub(crate) fn errs_apart(&self) -> bool {
        !matches!(self.soc, Some(0 | 2))
    }

    /// A client's write of `data` at `addr`, given in the default map, as
    /// the slave's map has it: `(addr, words)`. `sd` holds the switches'
    /// words in the default map; an `SD` write updates it.
    pub(crate) fn translate(
        &self,
        cmd: MebCmd,
        addr: u8,
        data: &[u16],
        sd: &mut [u16; 2],
    ) -> Result<(u8, MebWords), TranslateError> {
        if self.is_default() {
            let words = MebWords::from_slice(data).ok_or(TranslateError::NotInMap)?;
            return Ok((addr, words));
        }
        let (block, word_type) = cmd.block().ok_or(TranslateError::NotInMap)?;
        let written = usize::from(addr)..usize::from(addr) + data.len();
        if (block, word_type) == (MebBlock::Outputs, MebWordType::Digital) {
            for (index, word) in written.clone().zip(data) {
                *sd.get_mut(index).ok_or(TranslateError::NotInMap)? = *word;
            }
            let words = SWITCHES
                .iter()
                .zip(self.switches)
                .filter(|((_, home, _), _)| written.contains(&usize::from(*home)))
                .filter_map(|(_, place)| place.map(|(word, _)| word));
            let first = words.clone().min().ok_or(TranslateError::NotInMap)?;
            let last = words.clone().max().unwrap_or(first);
            let mut out = MebWords::new();
            for word in first..=last {
                if !self.switches.iter().flatten().any(|(w, _)| *w == word) {
                    return Err(TranslateError::Scattered);
                }
                let _ = out.push(self.sd_word(word, *sd));
            }
            return Ok((first, out));
        }
        let name = block_name(block, word_type);
        let mut placed = [None; 4];
        for (index, word) in written.zip(data) {
            let tag = TAGS
                .iter()
                .find(|t| {
                    t.block == block
                        && t.word_type == word_type
                        && t.bit.is_none()
                        && usize::from(t.index) == index
                })
                .ok_or(TranslateError::NotInMap)?;
            let (_, _, address, _) = self
                .map
                .placements()
                .find(|(b, n, _, _)| *b == name && *n == tag.name)
                .ok_or(TranslateError::NotInMap)?;
            let slot = placed
                .iter_mut()
                .find(|s| s.is_none())
                .ok_or(TranslateError::Scattered)?;
            *slot = Some((address, *word));
        }
        placed.sort_unstable_by_key(|p| p.map_or(u16::MAX, |(address, _)| u16::from(address)));
        let first = placed[0].map(|(a, _)| a).ok_or(TranslateError::NotInMap)?;
        let mut out = MebWords::new();
        for (expected, (address, word)) in (first..).zip(placed.iter().flatten()) {
            if *address != expected {
                return Err(TranslateError::Scattered);
            }
            let _ = out.push(*word);
        }
        Ok((first, out))
    }
}
