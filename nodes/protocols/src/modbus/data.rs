//! Fixed-capacity payloads of the multi-value function codes: packed bits
//! (coils, discrete inputs) and 16-bit registers. Sized for the largest legal
//! PDU so that no frame ever needs the heap.

use core::fmt;

use thiserror::Error;

/// Most packed bit bytes in one PDU: a read reply of 2000 bits.
pub const MAX_BIT_BYTES: usize = 250;
/// Most bits in one PDU (a read reply; a write request carries at most 1968).
pub const MAX_BITS: usize = MAX_BIT_BYTES * 8;
/// Most registers in one PDU: a read reply of 125 registers.
pub const MAX_REGISTERS: usize = 125;

/// More values than one PDU can carry.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
#[error("{len} values do not fit in one PDU (at most {max})")]
pub struct CapacityError {
    /// Values offered.
    pub len: usize,
    /// Values that fit.
    pub max: usize,
}

/// Bits packed eight to a byte, first bit in the least significant bit of the
/// first byte, as Modbus carries coils and discrete inputs.
///
/// The unused high bits of the last byte are kept as they arrived, so that a
/// parsed frame re-emits to the same bytes.
#[derive(Clone, PartialEq, Eq)]
pub struct Bits {
    quantity: u16,
    packed: [u8; MAX_BIT_BYTES],
}

impl Bits {
    /// No bits.
    pub const fn new() -> Self {
        Bits {
            quantity: 0,
            packed: [0; MAX_BIT_BYTES],
        }
    }

    /// Packs `values`.
    pub fn from_bools(values: &[bool]) -> Result<Self, CapacityError> {
        if values.len() > MAX_BITS {
            return Err(CapacityError {
                len: values.len(),
                max: MAX_BITS,
            });
        }
        let mut bits = Bits::new();
        for (i, &on) in values.iter().enumerate() {
            if on {
                bits.packed[i / 8] |= 1 << (i % 8);
            }
        }
        // The length check above keeps this in u16.
        bits.quantity = values.len() as u16;
        Ok(bits)
    }

    /// Takes `quantity` bits already packed in `packed`, which must be exactly
    /// `quantity.div_ceil(8)` bytes.
    pub fn from_packed(packed: &[u8], quantity: u16) -> Result<Self, CapacityError> {
        let needed = usize::from(quantity).div_ceil(8);
        if packed.len() > MAX_BIT_BYTES || needed != packed.len() {
            return Err(CapacityError {
                len: packed.len(),
                max: needed.min(MAX_BIT_BYTES),
            });
        }
        let mut bits = Bits::new();
        bits.packed[..packed.len()].copy_from_slice(packed);
        bits.quantity = quantity;
        Ok(bits)
    }

    /// Number of bits.
    pub fn quantity(&self) -> u16 {
        self.quantity
    }

    /// The packed bytes on the wire.
    pub fn packed(&self) -> &[u8] {
        let len = usize::from(self.quantity).div_ceil(8);
        self.packed.get(..len).unwrap_or(&[])
    }

    /// Bit `index`, `None` past the end.
    pub fn get(&self, index: usize) -> Option<bool> {
        if index >= usize::from(self.quantity) {
            return None;
        }
        self.packed
            .get(index / 8)
            .map(|byte| byte >> (index % 8) & 1 == 1)
    }

    /// The bits in order.
    pub fn iter(&self) -> impl Iterator<Item = bool> + '_ {
        (0..usize::from(self.quantity)).filter_map(|i| self.get(i))
    }
}

impl Default for Bits {
    fn default() -> Self {
        Bits::new()
    }
}

impl fmt::Debug for Bits {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Bits")
            .field("quantity", &self.quantity)
            .field("packed", &self.packed())
            .finish()
    }
}

/// 16-bit registers, big-endian on the wire.
#[derive(Clone, PartialEq, Eq)]
pub struct Registers {
    len: u8,
    values: [u16; MAX_REGISTERS],
}

impl Registers {
    /// No registers.
    pub const fn new() -> Self {
        Registers {
            len: 0,
            values: [0; MAX_REGISTERS],
        }
    }

    /// Copies `values`.
    pub fn from_slice(values: &[u16]) -> Result<Self, CapacityError> {
        let mut registers = Registers::new();
        let slot = registers
            .values
            .get_mut(..values.len())
            .ok_or(CapacityError {
                len: values.len(),
                max: MAX_REGISTERS,
            })?;
        slot.copy_from_slice(values);
        // At most 125, checked by the slice above.
        registers.len = values.len() as u8;
        Ok(registers)
    }

    /// Reads big-endian registers from `bytes` (an even number of them).
    pub(crate) fn from_be_bytes(bytes: &[u8]) -> Option<Self> {
        if !bytes.len().is_multiple_of(2) || bytes.len() / 2 > MAX_REGISTERS {
            return None;
        }
        let mut registers = Registers::new();
        for (slot, pair) in registers.values.iter_mut().zip(bytes.chunks_exact(2)) {
            *slot = u16::from_be_bytes([pair[0], pair[1]]);
        }
        registers.len = (bytes.len() / 2) as u8;
        Some(registers)
    }

    /// The registers.
    pub fn as_slice(&self) -> &[u16] {
        self.values.get(..usize::from(self.len)).unwrap_or(&[])
    }

    /// Number of registers.
    pub fn len(&self) -> usize {
        usize::from(self.len)
    }

    /// True when there are none.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

impl Default for Registers {
    fn default() -> Self {
        Registers::new()
    }
}

impl fmt::Debug for Registers {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_tuple("Registers").field(&self.as_slice()).finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bits_pack_lsb_first() {
        // Modbus application protocol example: coils 20..38 = CD 6B B2 0E 1B.
        let values = [
            true, false, true, true, false, false, true, true, // CD
            true, true, false, true, false, true, true, false, // 6B
            false, true, false, false, true, true, false, true, // B2
            false, true, true, true, false, false, false, false, // 0E
            true, true, false, true, true, // 1B (5 bits)
        ];
        let bits = Bits::from_bools(&values).unwrap();
        assert_eq!(bits.packed(), &[0xCD, 0x6B, 0xB2, 0x0E, 0x1B]);
        assert_eq!(bits.quantity(), 37);
        assert!(bits.iter().eq(values.iter().copied()));
        assert_eq!(bits.get(37), None);
    }

    #[test]
    fn capacities_are_enforced() {
        assert!(Bits::from_bools(&[false; MAX_BITS + 1]).is_err());
        assert!(Bits::from_packed(&[0; 3], 17).is_ok());
        assert!(Bits::from_packed(&[0; 3], 16).is_err());
        assert!(Registers::from_slice(&[0; MAX_REGISTERS + 1]).is_err());
        assert_eq!(Registers::from_slice(&[1, 2]).unwrap().as_slice(), &[1, 2]);
        assert!(Registers::from_be_bytes(&[1, 2, 3]).is_none());
        assert_eq!(
            Registers::from_be_bytes(&[0x12, 0x34]).unwrap().as_slice(),
            &[0x1234]
        );
    }
}
