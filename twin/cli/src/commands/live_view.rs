//! `--view` of `twin serve` and `twin supervise`: the viewer's rerun stream
//! as the real-time crate's [`LiveView`]. It lives here, in the binary,
//! because the binary is the one place that links both: the real-time crate
//! never links rerun, and the viewer knows nothing of real time.

use twin_realtime::sink::{LiveFrame, LiveView, ViewOpener};
use twin_view::logger::{LatenessSample, PlantSample};
use twin_view::{RerunObserver, Session, ViewLayout, ViewTarget};

/// A session streamed to rerun, and which role's session it is (so that the
/// link frames' senders get the view's names).
#[derive(Debug)]
struct RerunSession {
    observer: RerunObserver,
    session: Session,
}

impl LiveView for RerunSession {
    fn plant(&mut self, module: &str, t: f64, sensors: &plant::Sensors) {
        self.observer
            .logger
            .plant(module, t, &PlantSample::from(sensors));
    }

    fn event(&mut self, node: &str, t: f64, kind: &str, detail: &str) {
        self.observer.logger.event(node, t, kind, detail);
    }

    fn master_loop(&mut self, node: &str, t: f64, report: &serde_json::Value) {
        self.observer.logger.master_loop(node, t, report);
    }

    fn readings(&mut self, node: &str, t: f64, readings: &twin_recording::topics::ReadingsSample) {
        self.observer.logger.readings(node, t, readings);
    }

    fn lateness(&mut self, t: f64, p99_us: f64, max_us: f64) {
        self.observer
            .logger
            .lateness(t, &LatenessSample { p99_us, max_us });
    }

    fn frame(&mut self, f: &LiveFrame<'_>) {
        let from = self.session.sender(f.link, f.from, f.bytes);
        self.observer
            .logger
            .frame(f.link, &from, f.start, f.end, f.bytes);
    }

    fn finish(self: Box<Self>) -> (u64, Option<String>) {
        let samples = self.observer.logger.samples.values().sum();
        let error = self
            .observer
            .finish()
            .err()
            .map(|e| format!("{:#}", anyhow::Error::from(e)));
        (samples, error)
    }
}

/// The live view of `role`'s session at `target` (as `twin run --view`
/// takes it), laid out from the session's module names by `layout`. A view
/// that cannot open is said on stderr, and the session goes on without it.
pub fn opener(
    target: &str,
    role: &'static str,
    session: Session,
    layout: impl Fn(&[String]) -> ViewLayout + Send + Sync + 'static,
) -> ViewOpener {
    let target = ViewTarget::parse(target);
    ViewOpener::new(
        move |modules| match twin_view::live_view(&target, role, layout(modules)) {
            Ok(observer) => Some(Box::new(RerunSession { observer, session }) as Box<dyn LiveView>),
            Err(e) => {
                let e = anyhow::Error::from(e);
                eprintln!("{role} --view: {e:#}; running without the live view");
                None
            }
        },
    )
}
