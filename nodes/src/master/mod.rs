//! Masters: the supervisor that closes the speed loop over the bus.
