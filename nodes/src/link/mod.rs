//! Simulated media: bytes in, timed arrivals out.
