//! The lab's nodes and simulated media, all sans-IO: no sockets, no clock,
//! no unseeded randomness. Time comes in as [`protocols::time::SimTime`], bytes as
//! slices. The EV module controller (`firmware`), the Controller_network
//! project's Nanos and Raspberry Pi master (`controller_network`), the
//! supervisor and its server (`master`), the PWM-capture paper's parallel
//! nodes (`parallel`), and the RS-485 bus and PWM-capture line (`link`). The
//! codecs they speak are the `protocols` crate's, one import path for all.

pub mod controller_network;
pub mod firmware;
pub mod link;
pub mod master;
pub mod node;
pub mod parallel;
pub mod refusal;
