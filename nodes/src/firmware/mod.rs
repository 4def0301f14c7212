//! The EV module controller (seed 000): register image, MEB and Modbus RTU slave front ends, and the firmware loop.
