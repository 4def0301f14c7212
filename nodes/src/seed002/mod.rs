//! The seed-002 controller network: motor node (id 01), light-sensor node (id 02) and the Raspberry Pi master.
