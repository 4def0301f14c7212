//! The Modbus RTU slave front end: the fixed map of `docs/protocols/modbus-map.md` over
//! the same register image the MEB front end serves.

use protocols::modbus::{Bits, ExceptionResponse, Registers, Request, Response};

use super::image::{self, LDR_ADAPT, Refusal, RegisterImage, WriteSet, sd, status};

/// Input registers (FC 04): V2, I, V1, RPM_M, RPM_L, LDR, HALL, SOC, ERRS, STATUS.
pub const INPUT_REGISTERS: u16 = 10;
/// Holding registers (FC 03/06/16): VEL, LDR_TH, RPM_WIN.
pub const HOLDING_REGISTERS: u16 = 3;
/// Coils (FC 01/05/15): EN, BRK, PRO, DES, FR, CHG, two holes, LDR_ADAPT.
pub const COILS: u16 = 9;
/// Discrete inputs (FC 02): six STATUS bits, two holes, hall A, B, C, flag.
pub const DISCRETE_INPUTS: u16 = 12;

/// Longest read the map can answer in one request.
const MAX_TABLE: usize = 12;

/// Serves one request PDU addressed to `frame_unit`; returns the reply PDU.
/// Other units get silence; broadcasts (unit 0) execute writes and get silence.
pub fn serve(
    image: &mut RegisterImage,
    own_unit: u8,
    frame_unit: u8,
    pdu: &[u8],
) -> Option<Result<Response, ExceptionResponse>> {
    let broadcast = frame_unit == 0;
    if frame_unit != own_unit && !broadcast {
        return None;
    }
    let function = *pdu.first()?;
    let request = match Request::parse(pdu) {
        Ok(request) => request,
        Err(error) => {
            let exception = error.exception()?;
            return (!broadcast).then_some(Err(ExceptionResponse {
                function,
                exception,
            }));
        }
    };
    let is_read = matches!(
        request,
        Request::ReadCoils { .. }
            | Request::ReadDiscreteInputs { .. }
            | Request::ReadHoldingRegisters { .. }
            | Request::ReadInputRegisters { .. }
    );
    if broadcast && is_read {
        return None;
    }
    let answer = execute(image, &request).map_err(|refusal| ExceptionResponse {
        function,
        exception: refusal.modbus(),
    });
    (!broadcast).then_some(answer)
}

/// The reply when every request is refused with `refusal` (an injected
/// fault, a read-only client): the exception to a request for this unit;
/// silence to other units and to broadcasts. Nothing is stored.
pub fn refuse(
    own_unit: u8,
    frame_unit: u8,
    pdu: &[u8],
    refusal: Refusal,
) -> Option<Result<Response, ExceptionResponse>> {
    if frame_unit != own_unit || frame_unit == 0 {
        return None;
    }
    let function = *pdu.first()?;
    Some(Err(ExceptionResponse {
        function,
        exception: refusal.modbus(),
    }))
}

/// The first `quantity` table entries from `address`, or 02 past the table's end.
fn span(address: u16, quantity: u16, table: u16) -> Result<core::ops::Range<usize>, Refusal> {
    let end = u32::from(address) + u32::from(quantity);
    if end > u32::from(table) {
        return Err(Refusal::IllegalAddress);
    }
    Ok(usize::from(address)..end as usize)
}

fn input_register(image: &RegisterImage, index: usize) -> u16 {
    match index {
        0..image::EA_WORDS => image.inputs.get(index).copied().unwrap_or(0),
        6 => image.hall,
        7 => image.soc,
        8 => image.errs,
        9 => image.status,
        _ => 0,
    }
}

fn holding_register(image: &RegisterImage, index: usize) -> u16 {
    match index {
        0 => image.stored.vel,
        1 => image.stored.ldr_threshold,
        2 => image.stored.rpm_window_ms,
        _ => 0,
    }
}

/// Which word and bit a coil lives in; `None` for the holes.
#[derive(Debug, Clone, Copy)]
enum CoilWord {
    Sd0(u16),
    Sd1(u16),
    Vd0(u16),
}

fn coil_word(index: usize) -> Option<CoilWord> {
    match index {
        0..=4 => Some(CoilWord::Sd0(1 << index)),
        5 => Some(CoilWord::Sd1(sd::CHG)),
        8 => Some(CoilWord::Vd0(LDR_ADAPT)),
        _ => None,
    }
}

fn coil(image: &RegisterImage, index: usize) -> bool {
    let s = &image.stored;
    match coil_word(index) {
        Some(CoilWord::Sd0(bit)) => s.sd0 & bit != 0,
        Some(CoilWord::Sd1(bit)) => s.sd1 & bit != 0,
        Some(CoilWord::Vd0(bit)) => s.ldr_adaptive & bit != 0,
        None => false,
    }
}

fn discrete_input(image: &RegisterImage, index: usize) -> bool {
    match index {
        0..=5 => image.status & (1 << index) != 0,
        8..=11 => image.hall & (1 << (index - 8)) != 0,
        _ => false,
    }
}

/// Sets the coils `first..` to `values` in a write of the words they live in.
fn coil_write(
    image: &RegisterImage,
    first: usize,
    values: impl Iterator<Item = bool>,
) -> Result<WriteSet, Refusal> {
    let s = &image.stored;
    let mut set = WriteSet::default();
    let put = |word: Option<u16>, current: u16, bit: u16, on: bool| {
        let word = word.unwrap_or(current);
        Some(if on { word | bit } else { word & !bit })
    };
    for (index, on) in (first..).zip(values) {
        match coil_word(index).ok_or(Refusal::IllegalAddress)? {
            CoilWord::Sd0(bit) => set.sd0 = put(set.sd0, s.sd0, bit, on),
            CoilWord::Sd1(bit) => set.sd1 = put(set.sd1, s.sd1, bit, on),
            CoilWord::Vd0(bit) => set.ldr_adaptive = put(set.ldr_adaptive, s.ldr_adaptive, bit, on),
        }
    }
    Ok(set)
}

fn register_write(first: usize, values: &[u16]) -> WriteSet {
    let mut set = WriteSet::default();
    for (index, &value) in (first..).zip(values) {
        match index {
            0 => set.vel = Some(value),
            1 => set.ldr_threshold = Some(value),
            2 => set.rpm_window_ms = Some(value),
            // The span check keeps every index inside the table.
            _ => {}
        }
    }
    set
}

fn bits(range: core::ops::Range<usize>, bit: impl Fn(usize) -> bool) -> Bits {
    let mut values = [false; MAX_TABLE];
    let count = range.len().min(MAX_TABLE);
    for (slot, index) in values.iter_mut().zip(range) {
        *slot = bit(index);
    }
    Bits::from_bools(values.get(..count).unwrap_or(&[])).unwrap_or_default()
}

fn registers(range: core::ops::Range<usize>, register: impl Fn(usize) -> u16) -> Registers {
    let mut values = [0u16; MAX_TABLE];
    let count = range.len().min(MAX_TABLE);
    for (slot, index) in values.iter_mut().zip(range) {
        *slot = register(index);
    }
    Registers::from_slice(values.get(..count).unwrap_or(&[])).unwrap_or_default()
}

fn execute(image: &mut RegisterImage, request: &Request) -> Result<Response, Refusal> {
    match request {
        Request::ReadCoils { address, quantity } => {
            let range = span(*address, *quantity, COILS)?;
            Ok(Response::ReadCoils(bits(range, |i| coil(image, i))))
        }
        Request::ReadDiscreteInputs { address, quantity } => {
            let range = span(*address, *quantity, DISCRETE_INPUTS)?;
            Ok(Response::ReadDiscreteInputs(bits(range, |i| {
                discrete_input(image, i)
            })))
        }
        Request::ReadHoldingRegisters { address, quantity } => {
            let range = span(*address, *quantity, HOLDING_REGISTERS)?;
            Ok(Response::ReadHoldingRegisters(registers(range, |i| {
                holding_register(image, i)
            })))
        }
        Request::ReadInputRegisters { address, quantity } => {
            let range = span(*address, *quantity, INPUT_REGISTERS)?;
            Ok(Response::ReadInputRegisters(registers(range, |i| {
                input_register(image, i)
            })))
        }
        Request::WriteSingleCoil { address, value } => {
            let range = span(*address, 1, COILS)?;
            let set = coil_write(image, range.start, core::iter::once(*value))?;
            image.store(&set)?;
            Ok(Response::WriteSingleCoil {
                address: *address,
                value: *value,
            })
        }
        Request::WriteMultipleCoils { address, coils } => {
            let range = span(*address, coils.quantity(), COILS)?;
            let set = coil_write(image, range.start, coils.iter())?;
            image.store(&set)?;
            Ok(Response::WriteMultipleCoils {
                address: *address,
                quantity: coils.quantity(),
            })
        }
        Request::WriteSingleRegister { address, value } => {
            let range = span(*address, 1, HOLDING_REGISTERS)?;
            image.store(&register_write(range.start, &[*value]))?;
            Ok(Response::WriteSingleRegister {
                address: *address,
                value: *value,
            })
        }
        Request::WriteMultipleRegisters { address, registers } => {
            let values = registers.as_slice();
            let quantity = u16::try_from(values.len()).unwrap_or(u16::MAX);
            let range = span(*address, quantity, HOLDING_REGISTERS)?;
            image.store(&register_write(range.start, values))?;
            Ok(Response::WriteMultipleRegisters {
                address: *address,
                quantity,
            })
        }
    }
}

// The discrete inputs mirror STATUS bit for bit.
const _: () = assert!(status::CCW == 1 << 5);
