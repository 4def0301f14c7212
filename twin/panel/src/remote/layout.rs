//! Where the client panel finds each signal on the slave: the I/O map
//! (`--map`, the file `twin serve` reads) turned into the reads one poll
//! makes and the place of each output it writes.

use nodes::firmware::{MebMap, ea};
use nodes::master::MebLayout;
use protocols::meb::{MebBlock, MebWordType};

/// The analog inputs, as the lab's I/O list names them, with their
/// default-map word.
pub const INPUTS: [(&str, usize); 6] = [
    ("V2", ea::V2),
    ("I", ea::I),
    ("V1", ea::V1),
    ("RPM_M", ea::RPM_M),
    ("RPM_L", ea::RPM_L),
    ("LDR", ea::LDR),
];

/// The switches: name, default SD word and bit (the supervisor's table).
pub use nodes::master::SWITCHES;

/// A switch's place on the slave.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BitPlace {
    pub word: u8,
    pub bit: u8,
}

/// Every signal's address under one map.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Layout {
    /// `EA` word of each of [`INPUTS`], if the map places it.
    pub inputs: [Option<u8>; 6],
    /// What a poll reads of each block, as runs of neighbouring mapped
    /// addresses `(first, count)`: a mapped slave refuses (`ER 02`) a read
    /// that touches an address its map leaves empty.
    pub ea_reads: Vec<(u8, u8)>,
    pub hall: Option<u8>,
    pub ed_reads: Vec<(u8, u8)>,
    pub soc: Option<u8>,
    /// SOC and ERRS (ERRS keeps `FA 01` in every map).
    pub fa_reads: Vec<(u8, u8)>,
    pub vel: Option<u8>,
    pub switches: [Option<BitPlace>; 6],
    /// The SD words that hold a switch.
    pub sd_words: Vec<u8>,
}

/// The highest word address a map may use (CNT and ADDR are two digits).
const LAST: usize = 98;

/// Where the slave's error count sits, whatever the map (the firmware's own).
const ERRS: usize = 1;

/// `addresses` as runs of neighbours, lowest first: `(first, count)`.
fn runs(addresses: impl Iterator<Item = usize>) -> Vec<(u8, u8)> {
    let mut sorted: Vec<u8> = addresses.filter_map(|a| u8::try_from(a).ok()).collect();
    sorted.sort_unstable();
    sorted.dedup();
    let mut runs: Vec<(u8, u8)> = Vec::new();
    for a in sorted {
        match runs.last_mut() {
            Some((first, count)) if u16::from(*first) + u16::from(*count) == u16::from(a) => {
                *count += 1;
            }
            _ => runs.push((a, 1)),
        }
    }
    runs
}

impl Layout {
    /// Where the supervisor places each signal under `map` ([`MebLayout`],
    /// so the panel and the supervisor cannot disagree), and what a poll
    /// of every mapped address reads.
    pub fn new(map: &MebMap) -> Self {
        use MebBlock::Inputs;
        use MebWordType::{Analog, Digital};
        let supervisor = MebLayout::from_map(map);
        let switches: [Option<BitPlace>; 6] = std::array::from_fn(|i| {
            supervisor
                .switch_place(i)
                .map(|(word, bit)| BitPlace { word, bit })
        });
        let mut sd_words: Vec<u8> = switches.iter().flatten().map(|p| p.word).collect();
        sd_words.sort_unstable();
        sd_words.dedup();
        let mapped = |b, k| (0..=LAST).filter(move |&a| map.word(b, k, a).is_some());
        let soc = supervisor.soc_address();
        Self {
            inputs: std::array::from_fn(|i| supervisor.input_address(i)),
            ea_reads: runs(mapped(Inputs, Analog)),
            hall: supervisor.hall(),
            ed_reads: runs(mapped(Inputs, Digital)),
            soc,
            fa_reads: runs(soc.map(usize::from).into_iter().chain([ERRS])),
            vel: supervisor.vel_address(),
            switches,
            sd_words,
        }
    }

    /// Where the input `name` sits, as a label (`EA 02`).
    pub fn input_label(&self, i: usize) -> Option<String> {
        self.inputs[i].map(|a| format!("EA {a:02X}"))
    }

    /// Where switch `i` sits, as a label (`SD 00 bit 1`).
    pub fn switch_label(&self, i: usize) -> Option<String> {
        self.switches[i].map(|p| format!("SD {:02X} bit {}", p.word, p.bit))
    }
}

/// Writes where `layout` places each signal (`"at": "EA 02"`) into a
/// controller's `inputs` and `outputs`, as the page shows it.
pub fn label(controller: &mut serde_json::Value, layout: &Layout) {
    for (i, (name, _)) in INPUTS.iter().enumerate() {
        if let Some(v) = controller["inputs"].get_mut(*name) {
            v["at"] = layout.input_label(i).into();
        }
    }
    if let Some(v) = controller["inputs"].get_mut("SOC") {
        v["at"] = layout.soc.map(|a| format!("FA {a:02X}")).into();
    }
    if let Some(v) = controller["outputs"].get_mut("VEL") {
        v["at"] = layout.vel.map(|a| format!("SA {a:02X}")).into();
    }
    for (i, (name, ..)) in SWITCHES.iter().enumerate() {
        if let Some(v) = controller["outputs"].get_mut(*name) {
            v["at"] = layout.switch_label(i).into();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_map_is_the_protocol_pages_and_a_moved_signal_moves() {
        let d = Layout::new(&MebMap::default());
        assert_eq!(
            d.inputs,
            [Some(0), Some(1), Some(2), Some(3), Some(4), Some(5)]
        );
        assert_eq!(
            (d.ea_reads.as_slice(), d.vel, d.soc, d.hall),
            (&[(0, 6)][..], Some(0), Some(0), Some(0))
        );
        assert_eq!(
            (d.ed_reads.as_slice(), d.fa_reads.as_slice()),
            (&[(0, 1)][..], &[(0, 2)][..])
        );
        assert_eq!(d.switches[1], Some(BitPlace { word: 0, bit: 1 }));
        assert_eq!(d.switches[5], Some(BitPlace { word: 1, bit: 0 }));
        assert_eq!(d.sd_words, vec![0, 1]);
        let mut map = MebMap::default();
        map.clear_block("EA");
        map.place("EA", "V1", 0, None).unwrap();
        map.place("EA", "RPM_M", 7, None).unwrap();
        map.clear_block("SD");
        map.place("SD", "EN", 2, Some(5)).unwrap();
        let m = Layout::new(&map);
        assert_eq!(m.inputs[2], Some(0));
        assert_eq!(m.inputs[3], Some(7));
        assert_eq!(m.inputs[0], None, "V2 is not placed");
        assert_eq!(m.ea_reads, vec![(0, 1), (7, 1)], "only what the map places");
        assert_eq!(m.switch_label(0).as_deref(), Some("SD 02 bit 5"));
        assert_eq!(m.switches[1], None);
        assert_eq!(m.sd_words, vec![2]);
    }
}
