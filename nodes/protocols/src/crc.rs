//! The two checks of the Modbus family: CRC-16/MODBUS (RTU and the 8-byte
//! variant) and the longitudinal redundancy check of Modbus ASCII.
//!
//! Both are pure functions over byte slices; neither allocates nor panics.

use crc::{CRC_16_MODBUS, Crc};

/// CRC-16/MODBUS (the `crc` crate's catalogue entry): reflected polynomial
/// 0x8005, initial value 0xFFFF, no final XOR; check value for `b"123456789"`:
/// 0x4B37. One 256-entry table, built at compile time: one lookup and two
/// shifts per byte, as the hand-written table this replaced.
const MODBUS: Crc<u16> = Crc::<u16>::new(&CRC_16_MODBUS);

/// CRC-16/MODBUS of `data`, as a number.
///
/// Standard Modbus RTU sends it low byte first; the lab's 8-byte network sends it
/// high byte first. The byte order is the framing's business, not the CRC's.
pub fn crc16_modbus(data: &[u8]) -> u16 {
    MODBUS.checksum(data)
}

/// Continues a CRC-16/MODBUS over more bytes, starting from `crc` (0xFFFF for a
/// fresh computation), so a frame can be checked in pieces.
pub fn crc16_modbus_update(crc: u16, data: &[u8]) -> u16 {
    // The crate reflects an initial value as it reflects the input bytes; a
    // running CRC of this reflected algorithm is reflected already.
    let mut digest = MODBUS.digest_with_initial(crc.reverse_bits());
    digest.update(data);
    digest.finalize()
}

/// Modbus ASCII LRC of `data` (the binary bytes, before hex encoding): the two's
/// complement of their sum modulo 256.
pub fn lrc(data: &[u8]) -> u8 {
    data.iter()
        .fold(0u8, |sum, &byte| sum.wrapping_add(byte))
        .wrapping_neg()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bit-by-bit reference, straight from the Modbus serial line specification.
    fn crc_bitwise(data: &[u8]) -> u16 {
        let mut crc = 0xFFFFu16;
        for &byte in data {
            crc ^= u16::from(byte);
            for _ in 0..8 {
                crc = if crc & 1 != 0 {
                    (crc >> 1) ^ 0xA001
                } else {
                    crc >> 1
                };
            }
        }
        crc
    }

    #[test]
    fn crc_check_value() {
        assert_eq!(crc16_modbus(b"123456789"), 0x4B37);
        assert_eq!(crc16_modbus(b""), 0xFFFF);
    }

    #[test]
    fn table_matches_bitwise_reference() {
        let data: Vec<u8> = (0..=255u8).chain((0..=255u8).rev()).collect();
        for len in 0..data.len() {
            assert_eq!(
                crc16_modbus(&data[..len]),
                crc_bitwise(&data[..len]),
                "{len}"
            );
        }
    }

    #[test]
    fn crc_can_be_computed_in_pieces() {
        let whole = crc16_modbus(b"0106000100");
        let pieces = crc16_modbus_update(crc16_modbus(b"0106"), b"000100");
        assert_eq!(whole, pieces);
    }

    #[test]
    fn crc_of_a_known_rtu_frame() {
        // Modbus application note example: 01 03 00 00 00 0A -> C5 CD on the wire
        // (low byte first), i.e. 0xCDC5.
        assert_eq!(crc16_modbus(&[0x01, 0x03, 0x00, 0x00, 0x00, 0x0A]), 0xCDC5);
        // The Controller_network project's frame 01 06 0001 0080 carries aa d9 high byte first.
        assert_eq!(crc16_modbus(&[0x01, 0x06, 0x00, 0x01, 0x00, 0x80]), 0xAAD9);
    }

    #[test]
    fn lrc_of_known_frames() {
        // Modbus over serial line spec example ":F7031389000A60\r\n".
        assert_eq!(lrc(&[0xF7, 0x03, 0x13, 0x89, 0x00, 0x0A]), 0x60);
        assert_eq!(lrc(&[]), 0);
        // The sum of the data and its LRC is zero modulo 256.
        let data = [0x11, 0x03, 0x00, 0x6B, 0x00, 0x03];
        let sum = data.iter().fold(lrc(&data), |s, &b| s.wrapping_add(b));
        assert_eq!(sum, 0);
    }
}
