//! What the engine is built from besides its devices: links and the faults
//! the console switches on.

use nodes::firmware::Refusal;
use nodes::link::{CheckKind, Junk};
use protocols::time::SimDuration;

use super::device::Device;
use super::endpoint::Endpoint;
use crate::io::LinkSpec;

/// A fault switched on from the console, applied to replies as they leave.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkFault {
    /// Replies go out with their check value plus one.
    BadCheck,
    /// Replies are lost.
    NoReply,
    /// Replies go out this much later.
    Delay(SimDuration),
    /// Every request is answered with this refusal (exception / ER).
    Exception(Refusal),
    /// Replies carry this id (`None`: the slave's own + 1), their check good.
    WrongId(Option<u8>),
    /// Replies go in two writes, the second `gap` after the first ends.
    Split(SimDuration),
    /// Junk bytes go with every reply.
    Junk(Junk),
}

/// The fault as the console's `fault` command names it; an exception with
/// its name in both protocols (the Modbus specification's, the MEB page's).
impl std::fmt::Display for LinkFault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LinkFault::BadCheck => f.write_str("bad-check"),
            LinkFault::NoReply => f.write_str("no-reply"),
            LinkFault::Delay(d) => write!(f, "delay {:.0} ms", d.as_secs_f64() * 1000.0),
            LinkFault::Exception(refusal) => {
                let (modbus, meb) = (refusal.modbus(), refusal.meb());
                write!(
                    f,
                    "exception {:02} (Modbus {}, MEB ER {:02} {})",
                    meb.word(),
                    modbus.name(),
                    meb.word(),
                    meb.name()
                )
            }
            LinkFault::WrongId(Some(id)) => write!(f, "wrong-id (replies as id {id})"),
            LinkFault::WrongId(None) => f.write_str("wrong-id (replies as the next id)"),
            LinkFault::Split(gap) => write!(
                f,
                "split (replies in two writes, {:.1} ms apart)",
                gap.as_secs_f64() * 1000.0
            ),
            LinkFault::Junk(junk) => write!(f, "{junk}"),
        }
    }
}

/// Makes the endpoint for a new connection on a link: (devices, peer).
pub type EndpointFactory = Box<dyn FnMut(&mut [Device], &str) -> Box<dyn Endpoint> + Send>;

/// One configured link.
pub struct LinkConfig {
    /// Unique name, for the monitor and the recording's topic.
    pub name: String,
    /// Protocol as printed: `meb`, `modbus-tcp`, `modbus-rtu`, `modbus-ascii`, `modbus8`.
    pub protocol: &'static str,
    /// Resolved address (real port, device path).
    pub address: String,
    /// The twin is the master here (the supervisor's bus): the frames that
    /// come in are slaves' replies, not clients' requests.
    pub twin_is_master: bool,
    pub spec: LinkSpec,
    /// Where a bad-check fault spoils a reply.
    pub check: Option<CheckKind>,
    /// Close a connection holding a partial frame this long (TCP).
    pub partial_timeout: Option<SimDuration>,
    /// Close a connection that sends more bytes than this in one second (TCP).
    pub rate_limit: Option<u64>,
    /// Close a connection that has sent nothing for this long (TCP).
    pub idle_timeout: Option<SimDuration>,
    pub factory: EndpointFactory,
}

impl std::fmt::Debug for LinkConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LinkConfig")
            .field("name", &self.name)
            .field("address", &self.address)
            .finish_non_exhaustive()
    }
}
