//! twin-sim's integration tests: scenario files run end to end.

mod fault_kinds;
