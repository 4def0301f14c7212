//! The panel's API and the page in a real browser.
//!
//! One test binary for the crate: each module is one area, and the
//! shared helpers are compiled once.

#![allow(
    clippy::disallowed_methods,
    reason = "the tests drive a real server and a real browser in real time"
)]

mod api;
mod browser;
mod class_browser;
mod client_browser;
mod client_truth;
mod common;
mod meb_bus;
mod page;
mod phone_layout;
mod scope;
mod serve_truth;
mod sim_inputs;
mod supervise_browser;
mod supervise_slaves;
mod supervise_truth;
