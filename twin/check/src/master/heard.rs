//! What the twin heard of a master in each situation: its requests, what
//! the twin answered, and the frames as evidence. Played by `play`, judged
//! by `judge`.

use super::dialect::Examined;
use crate::run::Exchange;

/// One request the master sent, and what the twin did with it.
#[derive(Debug, Clone)]
pub(crate) struct Heard {
    /// When its last byte came, seconds after the link was opened.
    pub at: f64,
    pub bytes: Vec<u8>,
    /// Bytes before it that belonged to no frame (MEB: before its `@`).
    pub junk: Vec<u8>,
    /// What the slave made of it: its faults, its slave, what it reads.
    pub seen: Examined,
    /// It came while the twin still owed a reply to an earlier one.
    pub owed: bool,
    pub answer: Option<Answer>,
}

/// What the twin sent back to a request.
#[derive(Debug, Clone, Default)]
pub(crate) struct Answer {
    /// When its last byte was written.
    pub end: f64,
    /// It was spoilt (bad FCS, another id) or an error reply: not the
    /// slave's normal reply.
    pub spoilt: bool,
    /// The good reply, sent after a spoilt one when the master neither
    /// retried nor went on.
    pub rescued: bool,
}

/// One situation as it went.
#[derive(Debug, Default)]
pub(crate) struct Phase {
    pub heard: Vec<Heard>,
    pub frames: Vec<Exchange>,
    /// When it began, seconds after the link was opened, and how long.
    pub began: f64,
    pub seconds: f64,
}
