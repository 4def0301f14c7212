//! twin-sim's integration tests: scenario files run end to end.

mod captures;
mod fault_kinds;
