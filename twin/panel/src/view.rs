//! The panel as the sink's live view: frames, events and the tick lateness
//! go into the hub (the engine's state is read another way, see
//! [`crate::snapshot`]); and [`Tee`], which feeds two views at once (rerun
//! and the panel).

use serde_json::Value;
use std::sync::Arc;

use crate::hub::Hub;
use twin_realtime::sink::{LiveFrame, LiveView};
use twin_recording::topics::ReadingsSample;

/// Feeds a [`Hub`].
#[derive(Debug)]
pub struct PanelView {
    hub: Arc<Hub>,
}

impl PanelView {
    pub fn new(hub: Arc<Hub>) -> Self {
        Self { hub }
    }
}

impl LiveView for PanelView {
    // The plant's state comes with the engine's (one read for every client).
    fn plant(&mut self, _module: &str, _t: f64, _sensors: &plant::Sensors) {}

    fn event(&mut self, node: &str, t: f64, kind: &str, detail: &str) {
        if kind != "log" {
            self.hub.push_event(node, t, kind, detail);
        }
    }

    fn master_loop(&mut self, _node: &str, _t: f64, _report: &Value) {}

    fn readings(&mut self, _node: &str, _t: f64, _readings: &ReadingsSample) {}

    fn lateness(&mut self, _t: f64, p99_us: f64, max_us: f64) {
        self.hub.set_lateness(p99_us, max_us);
    }

    fn frame(&mut self, f: &LiveFrame<'_>) {
        self.hub.push_frame(f);
    }

    fn finish(self: Box<Self>) -> (u64, Option<String>) {
        (0, None)
    }
}

/// Two live views fed the same: the first one's count and error are the
/// session's (the rerun view's, when both run).
#[derive(Debug)]
pub struct Tee(pub Box<dyn LiveView>, pub Box<dyn LiveView>);

impl LiveView for Tee {
    fn plant(&mut self, module: &str, t: f64, sensors: &plant::Sensors) {
        self.0.plant(module, t, sensors);
        self.1.plant(module, t, sensors);
    }
    fn event(&mut self, node: &str, t: f64, kind: &str, detail: &str) {
        self.0.event(node, t, kind, detail);
        self.1.event(node, t, kind, detail);
    }
    fn master_loop(&mut self, node: &str, t: f64, report: &Value) {
        self.0.master_loop(node, t, report);
        self.1.master_loop(node, t, report);
    }
    fn readings(&mut self, node: &str, t: f64, readings: &ReadingsSample) {
        self.0.readings(node, t, readings);
        self.1.readings(node, t, readings);
    }
    fn lateness(&mut self, t: f64, p99_us: f64, max_us: f64) {
        self.0.lateness(t, p99_us, max_us);
        self.1.lateness(t, p99_us, max_us);
    }
    fn frame(&mut self, f: &LiveFrame<'_>) {
        self.0.frame(f);
        self.1.frame(f);
    }
    fn finish(self: Box<Self>) -> (u64, Option<String>) {
        let _ = self.1.finish();
        self.0.finish()
    }
}
