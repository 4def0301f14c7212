//! One remote MEB client of the supervisor, as the real-time engine drives it:
//! its bytes go to an [`ImageServer`] that answers from the supervisor's image
//! and forwards writes on the bus.

use nodes::master::image_server::{ClientId, ImageServer, ImageServerConfig};
use nodes::node::NodeEvent;
use protocols::time::SimTime;

use crate::{Device, Endpoint};

/// The endpoint of one TCP client. Each connection has its own server state
/// (framing, replies owed in order); all of them share the supervisor.
#[derive(Debug)]
pub struct ImageEndpoint {
    /// Index of the supervisor among the engine's devices.
    pub device: usize,
    server: ImageServer,
    client: ClientId,
}

impl ImageEndpoint {
    /// A new client at `now`. The client limit is kept by the listener, and
    /// the partial-frame timeout by the engine (from [`Endpoint::pending`]).
    pub fn new(device: usize, mut config: ImageServerConfig, now: SimTime) -> Self {
        config.max_clients = 1;
        // The engine times partial frames out and closes the connection; a
        // decoder that dropped them first would hide them from it.
        config.partial_timeout = protocols::time::SimDuration(u64::MAX / 4);
        let mut server = ImageServer::new(config);
        let client = server
            .accept(now)
            .unwrap_or_else(|_| unreachable!("a one-client server accepts its first client"));
        Self {
            device,
            server,
            client,
        }
    }
}

impl Endpoint for ImageEndpoint {
    fn handle_bytes(&mut self, devices: &mut [Device], now: SimTime, bytes: &[u8]) {
        if let Some(supervisor) = devices
            .get_mut(self.device)
            .and_then(|d| d.node.supervisor_mut())
        {
            self.server
                .handle_bytes(now, self.client, bytes, supervisor);
        }
    }

    fn handle_timeout(&mut self, _devices: &mut [Device], _now: SimTime) {}

    fn poll_timeout(&self, _devices: &[Device]) -> Option<SimTime> {
        None
    }

    fn poll_transmit(
        &mut self,
        devices: &mut [Device],
        now: SimTime,
        buf: &mut [u8],
    ) -> Option<usize> {
        if let Some(supervisor) = devices
            .get_mut(self.device)
            .and_then(|d| d.node.supervisor_mut())
        {
            self.server.collect(supervisor);
            // With the bus gone the supervisor is not driven: its queued
            // writes would never go out.
            self.server.expire(now, supervisor);
        }
        self.server.poll_transmit(self.client, buf)
    }

    fn poll_event(&mut self, _devices: &mut [Device]) -> Option<(String, NodeEvent)> {
        None
    }

    fn pending(&self) -> usize {
        self.server.pending(self.client)
    }

    fn requests(&self) -> Option<u64> {
        Some(
            self.server
                .client_stats(self.client)
                .map_or(0, |stats| stats.requests),
        )
    }

    fn noise_bytes(&self) -> u64 {
        self.server
            .decoder_stats(self.client)
            .map_or(0, |stats| stats.noise_bytes)
    }

    /// A write is answered once the slave has answered it on the bus.
    fn answers_later(&self) -> bool {
        true
    }

    fn close_request(&self) -> Option<String> {
        self.server
            .close_reason(self.client)
            .map(|why| why.to_string())
    }
}
