//! Which client addresses a TCP link serves (`--allow`): ports and slave
//! ids are not access control, so a class's modules each name the students'
//! machines that may reach them. A client from elsewhere is closed at once
//! and the refusal logged. The list can be changed while the session runs
//! (SIGHUP rereads a configuration file's).

use std::net::IpAddr;
use std::sync::{Arc, RwLock};

use ipnet::IpNet;

/// One allowed network (`10.0.3.0/24`, `127.0.0.1/32`, `::1/128`; no
/// prefix: the one address).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Network(IpNet);

impl Network {
    /// Parses `ADDRESS[/PREFIX]`; the error says what was wrong in words.
    pub fn parse(text: &str) -> Result<Self, String> {
        let text = text.trim();
        let net = match text.split_once('/') {
            Some((addr, _)) => {
                let addr: IpAddr = addr.parse().map_err(|_| not_a_network(text))?;
                let max = if addr.is_ipv4() { 32 } else { 128 };
                text.parse::<IpNet>()
                    .map_err(|_| format!("`{text}`: the prefix length must be 0 to {max}"))?
            }
            None => IpNet::from(text.parse::<IpAddr>().map_err(|_| not_a_network(text))?),
        };
        Ok(Self(net))
    }

    /// Whether `ip` is in this network (an IPv4 client seen as
    /// `::ffff:a.b.c.d` on a dual-stack socket counts as `a.b.c.d`).
    pub fn contains(&self, ip: IpAddr) -> bool {
        let ip = match ip {
            IpAddr::V6(v6) => v6.to_ipv4_mapped().map_or(ip, IpAddr::V4),
            v4 => v4,
        };
        self.0.contains(&ip)
    }
}

fn not_a_network(text: &str) -> String {
    format!("`{text}` is not an address or network like 10.0.3.0/24 or 127.0.0.1")
}

impl std::fmt::Display for Network {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.0.fmt(f)
    }
}

/// The networks a link's clients may come from; shared with its listener,
/// so a reread configuration takes effect for the next client.
#[derive(Debug, Clone, Default)]
pub struct AllowList(Arc<RwLock<Vec<Network>>>);

impl AllowList {
    pub fn new(networks: Vec<Network>) -> Self {
        Self(Arc::new(RwLock::new(networks)))
    }

    /// Whether a client from `ip` is served (an empty list serves everyone).
    pub fn permits(&self, ip: IpAddr) -> bool {
        let networks = self.0.read().unwrap_or_else(|e| e.into_inner());
        networks.is_empty() || networks.iter().any(|n| n.contains(ip))
    }

    /// Replaces the networks (for clients that come from now on).
    pub fn set(&self, networks: Vec<Network>) {
        *self.0.write().unwrap_or_else(|e| e.into_inner()) = networks;
    }

    /// The networks, as the refusal names them: `127.0.0.1/32, 10.0.3.0/24`.
    pub fn shown(&self) -> String {
        let networks = self.0.read().unwrap_or_else(|e| e.into_inner());
        networks
            .iter()
            .map(ToString::to_string)
            .collect::<Vec<_>>()
            .join(", ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[test]
    fn networks_hold_their_addresses_and_no_others() {
        let lo = Network::parse("127.0.0.1/32").unwrap();
        assert!(lo.contains(ip("127.0.0.1")));
        assert!(!lo.contains(ip("127.0.0.2")));
        assert!(lo.contains(ip("::ffff:127.0.0.1")));
        let lab = Network::parse("10.0.3.0/24").unwrap();
        assert!(lab.contains(ip("10.0.3.77")));
        assert!(!lab.contains(ip("10.0.4.1")));
        assert!(Network::parse("0.0.0.0/0").unwrap().contains(ip("8.8.8.8")));
        assert!(Network::parse("::1").unwrap().contains(ip("::1")));
        assert!(!Network::parse("::1").unwrap().contains(ip("127.0.0.1")));
        assert!(Network::parse("10.0.3.0/33").is_err());
        assert!(Network::parse("lab-pc-7").is_err());
        let list = AllowList::new(vec![lo, lab]);
        assert!(list.permits(ip("10.0.3.5")));
        assert!(!list.permits(ip("192.168.1.1")));
        assert_eq!(list.shown(), "127.0.0.1/32, 10.0.3.0/24");
        assert!(AllowList::default().permits(ip("192.168.1.1")));
    }
}
