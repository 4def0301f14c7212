//! A device: a node with a plant or an image (the EV controller, a
//! Controller_network Nano, a supervisor), as the real-time engine and the
//! endpoints that answer for it see it.

use protocols::time::SimTime;

use super::forces::{Forces, HallLines};
use twin_sim::engine::SimNode;

/// A node with a plant or an image: the EV controller, a Controller_network Nano,
/// a supervisor.
pub struct Device {
    pub name: String,
    pub node: Box<dyn SimNode + Send>,
    pub module: Option<usize>,
    /// Inputs the user forced from the console or the panel.
    pub forces: Forces,
    /// The hall lines the controller sees, once a code has been forced.
    pub(super) hall_lines: HallLines,
    /// Where its slave answers (id and MEB I/O map), when the session lets
    /// the user change it while it runs (`twin serve`'s EV controller);
    /// each new connection's front end is made with it.
    pub address: Option<SlaveAddress>,
    pub(super) next_tick: Option<SimTime>,
    /// Its node has failed (a sketch crashed or stopped answering), and the
    /// console has been told.
    pub(super) failed: bool,
}

impl Device {
    pub fn new(name: &str, mut node: Box<dyn SimNode + Send>, module: Option<usize>) -> Self {
        let next_tick = node.firmware().map(|_| SimTime::ZERO);
        Self {
            name: name.into(),
            node,
            module,
            forces: Forces::default(),
            hall_lines: HallLines::default(),
            address: None,
            next_tick,
            failed: false,
        }
    }
}

/// A slave's device number and I/O map (the M3CVME tool's "device number"
/// and "mapping of the I/O signals").
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SlaveAddress {
    /// MEB slave number, Modbus unit id.
    pub id: u8,
    /// Where MEB links place the signals (the default map when `None`).
    pub meb_map: Option<nodes::firmware::MebMap>,
}

impl std::fmt::Debug for Device {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Device")
            .field("name", &self.name)
            .finish_non_exhaustive()
    }
}
