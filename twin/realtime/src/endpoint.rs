//! What sits at the twin's end of one real connection (a serial port, a TCP
//! client): a sans-IO [`Endpoint`] the real-time engine feeds with the bytes
//! that arrived and asks for the frames to send.
//!
//! Two kinds cover every role:
//! - [`NodeEndpoint`] drives whole [`Node`](nodes::node::Node)s (the
//!   Controller_network Nanos behind one port, a supervisor polling a serial line): the
//!   link's bytes go to each node, each node's frames go out on the link.
//! - [`SlaveEndpoint`] serves a device's register image through its own
//!   [`SlaveFrontend`] (framing and reply queue per connection, one image
//!   for all): MEB and Modbus TCP clients, RTU or ASCII on a port.

use std::collections::VecDeque;

use nodes::firmware::SlaveFrontend;
use nodes::node::{MAX_FRAME, NodeEvent};
use protocols::time::SimTime;

use super::device::Device;

/// One connection's protocol end, driven by the real-time engine.
pub trait Endpoint: Send {
    /// Bytes that arrived at `now`.
    fn handle_bytes(&mut self, devices: &mut [Device], now: SimTime, bytes: &[u8]);
    /// The instant asked for through [`Endpoint::poll_timeout`] has come.
    fn handle_timeout(&mut self, devices: &mut [Device], now: SimTime);
    /// The next instant the endpoint needs to be woken at, if any.
    fn poll_timeout(&self, devices: &[Device]) -> Option<SimTime>;
    /// The next firmware loop tick the engine should run between its 1 ms
    /// ticks, if any: a sketch that owes a reply is run on its own loop
    /// period, so the reply leaves when the sketch has written it (an
    /// instant of no link's, so the engine sleeps to it without spinning).
    fn follow(&self, _devices: &[Device]) -> Option<SimTime> {
        None
    }
    /// A frame to send now, written to `buf`; its length.
    fn poll_transmit(
        &mut self,
        devices: &mut [Device],
        now: SimTime,
        buf: &mut [u8],
    ) -> Option<usize>;
    /// The last frame has been written to the link at `now`: when its
    /// carrier wrote it if [`Endpoint::reports_writes`], else when the
    /// engine handed it to the carrier.
    fn transmit_done(&mut self, _devices: &mut [Device], _now: SimTime) {}
    /// Whether [`Endpoint::transmit_done`] waits for the carrier to have
    /// written the frame, and the frame is recorded as written then: a
    /// master's reply timeout counts from when its request has left, which
    /// on a busy machine (or across a stopped process) comes later than the
    /// engine's hand-off. Costs the carrier a lock of the front per write,
    /// so a slave's endpoint, whose replies wait for nothing, says no. The
    /// tokio carriers report (serial ports, the connections the twin opens
    /// itself: where it is a master); a listener's client threads do not.
    fn reports_writes(&self) -> bool {
        false
    }
    /// Take the next event the endpoint itself noticed: (who, the event).
    fn poll_event(&mut self, devices: &mut [Device]) -> Option<(String, NodeEvent)>;
    /// Bytes held for a frame that is not complete yet (partial-frame timeout).
    fn pending(&self) -> usize {
        0
    }
    /// Well-formed requests taken so far (`None`: the endpoint does not
    /// count them); a newcomer on probation earns its place with the first.
    fn requests(&self) -> Option<u64> {
        None
    }
    /// Bytes thrown away so far as noise, outside any frame: a connection
    /// that sends only these is as quiet as one that sends nothing.
    fn noise_bytes(&self) -> u64 {
        0
    }
    /// The slave front end, for faults and read-only switches.
    fn frontend_mut(&mut self) -> Option<&mut SlaveFrontend> {
        None
    }
    /// The device whose image its front end serves, if it has one.
    fn served_device(&self) -> Option<usize> {
        None
    }
    /// Whether a reply may become due with neither new bytes nor a deadline
    /// of [`Endpoint::poll_timeout`] (it waits on another link): then the
    /// engine's passes look for it, and its connection's carrier listens for
    /// their wake-ups.
    fn answers_later(&self) -> bool {
        false
    }
    /// Why the endpoint wants its connection closed (a limit it keeps itself).
    fn close_request(&self) -> Option<String> {
        None
    }
}

/// Drives the nodes of `devices` (indices into the engine's devices) over
/// one link, as the simulated bus does: every node hears every byte.
#[derive(Debug, Clone, Default)]
pub struct NodeEndpoint {
    pub devices: Vec<usize>,
    /// Replies taken from the nodes in the order their requests came (see
    /// `handle_bytes`), back to back, and their lengths.
    replies: Vec<u8>,
    lengths: VecDeque<usize>,
    /// Where a node writes a frame, made once: `collect` runs for every byte.
    scratch: Vec<u8>,
    /// The nodes are masters: see [`Endpoint::reports_writes`].
    masters: bool,
}

impl NodeEndpoint {
    /// Drives `devices` over one link.
    pub fn new(devices: Vec<usize>) -> Self {
        NodeEndpoint {
            devices,
            scratch: vec![0; MAX_FRAME],
            ..Self::default()
        }
    }

    /// Drives masters (`devices`) over one link: each is told its request
    /// has left when its carrier has written it, and its reply timeout
    /// runs from then.
    pub fn masters(devices: Vec<usize>) -> Self {
        NodeEndpoint {
            masters: true,
            ..Self::new(devices)
        }
    }

    /// Takes every frame the nodes have ready, in node order.
    fn collect(&mut self, devices: &mut [Device], now: SimTime) {
        for &d in &self.devices {
            let Some(device) = devices.get_mut(d) else {
                continue;
            };
            while let Some(n) = device.node.poll_transmit(now, &mut self.scratch) {
                let frame = self.scratch.get(..n).unwrap_or_default();
                self.replies.extend_from_slice(frame);
                self.lengths.push_back(n);
            }
        }
    }
}

impl Endpoint for NodeEndpoint {
    fn handle_bytes(&mut self, devices: &mut [Device], now: SimTime, bytes: &[u8]) {
        if let [one] = self.devices[..] {
            if let Some(device) = devices.get_mut(one) {
                device.node.handle_bytes(now, bytes);
            }
            return;
        }
        // Several nodes on one line, and a write of several requests (a
        // pty or TCP has no line timing to space them): each node is fed a
        // byte at a time and its replies are taken as they come, so the
        // line answers in the order it was asked, as on the bench, where
        // each board answers its request before the next one arrives.
        for &byte in bytes {
            for &d in &self.devices {
                if let Some(device) = devices.get_mut(d) {
                    device.node.handle_bytes(now, &[byte]);
                }
            }
            self.collect(devices, now);
        }
    }

    fn handle_timeout(&mut self, devices: &mut [Device], now: SimTime) {
        for &d in &self.devices {
            if let Some(device) = devices.get_mut(d)
                && device.node.poll_timeout().is_some_and(|t| t <= now)
            {
                device.node.handle_timeout(now);
            }
        }
    }

    fn poll_timeout(&self, devices: &[Device]) -> Option<SimTime> {
        self.devices
            .iter()
            .filter_map(|&d| devices.get(d)?.node.poll_timeout())
            .min()
    }

    fn poll_transmit(
        &mut self,
        devices: &mut [Device],
        now: SimTime,
        buf: &mut [u8],
    ) -> Option<usize> {
        if let Some(len) = self.lengths.pop_front() {
            let n = len.min(buf.len()).min(self.replies.len());
            buf.get_mut(..n)?.copy_from_slice(self.replies.get(..n)?);
            self.replies.drain(..len.min(self.replies.len()));
            return Some(n);
        }
        self.devices
            .iter()
            .find_map(|&d| devices.get_mut(d)?.node.poll_transmit(now, buf))
    }

    fn transmit_done(&mut self, devices: &mut [Device], now: SimTime) {
        for &d in &self.devices {
            if let Some(device) = devices.get_mut(d) {
                device.node.transmit_done(now);
            }
        }
    }

    fn reports_writes(&self) -> bool {
        self.masters
    }

    /// The engine drains the devices' own events, whatever drives them.
    fn poll_event(&mut self, _devices: &mut [Device]) -> Option<(String, NodeEvent)> {
        None
    }
}

/// Serves the register image of device `device` through `frontend`.
#[derive(Debug, Clone)]
pub struct SlaveEndpoint {
    pub device: usize,
    pub frontend: SlaveFrontend,
    /// Name for events: the device and the link.
    pub name: String,
}

impl Endpoint for SlaveEndpoint {
    fn handle_bytes(&mut self, devices: &mut [Device], now: SimTime, bytes: &[u8]) {
        if let Some(image) = devices
            .get_mut(self.device)
            .and_then(|d| d.node.image_mut())
        {
            self.frontend.handle_bytes(image, now, bytes);
        }
    }

    fn handle_timeout(&mut self, devices: &mut [Device], now: SimTime) {
        if let Some(image) = devices
            .get_mut(self.device)
            .and_then(|d| d.node.image_mut())
        {
            self.frontend.handle_timeout(image, now);
        }
    }

    fn poll_timeout(&self, _devices: &[Device]) -> Option<SimTime> {
        self.frontend.poll_timeout()
    }

    fn poll_transmit(
        &mut self,
        _devices: &mut [Device],
        _now: SimTime,
        buf: &mut [u8],
    ) -> Option<usize> {
        self.frontend.poll_transmit(buf)
    }

    fn poll_event(&mut self, _devices: &mut [Device]) -> Option<(String, NodeEvent)> {
        let event = self.frontend.poll_event()?;
        Some((self.name.clone(), event))
    }

    fn pending(&self) -> usize {
        self.frontend.pending()
    }

    fn noise_bytes(&self) -> u64 {
        self.frontend.noise_bytes()
    }

    fn requests(&self) -> Option<u64> {
        Some(self.frontend.stats().requests)
    }

    fn frontend_mut(&mut self) -> Option<&mut SlaveFrontend> {
        Some(&mut self.frontend)
    }

    fn served_device(&self) -> Option<usize> {
        Some(self.device)
    }

    fn close_request(&self) -> Option<String> {
        self.frontend.close_request().map(str::to_string)
    }
}
