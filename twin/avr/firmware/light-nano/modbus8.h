// The Controller_network project's 8-byte Modbus, slave side
// (docs/protocols/modbus8.md): every frame is id, function, address (2),
// value (2), CRC-16/MODBUS over the first six bytes, high byte first.
// The same file sits in motor-nano and light-nano on purpose: each sketch
// folder opens and builds on its own in the Arduino IDE, as the boards' do.
#pragma once
#include <Arduino.h>

static const uint8_t FRAME_LEN = 8;
static const uint8_t FN_READ = 0x03, FN_WRITE = 0x06;
static const uint8_t EX_FUNCTION = 0x01, EX_ADDRESS = 0x02, EX_VALUE = 0x03;
// 3.5 characters of quiet at 115200 baud (10 bits each) ends a partial frame.
static const uint32_t SILENCE_US = 304;

static uint16_t crc16(const uint8_t *b, uint8_t n) {
  uint16_t crc = 0xFFFF;
  for (uint8_t i = 0; i < n; i++) {
    crc ^= b[i];
    for (uint8_t k = 0; k < 8; k++) crc = (crc & 1) ? (crc >> 1) ^ 0xA001 : crc >> 1;
  }
  return crc;
}

static uint8_t frame[FRAME_LEN];
static uint8_t frame_len;
static uint32_t last_byte_us;

// What the sketch answers: fills value with the register on a read, stores
// it on a write; returns 0 or an exception code, checked in the page's
// order (address, then function, then value).
typedef uint8_t (*Handler)(uint8_t function, uint16_t addr, uint16_t *value);

static void send_frame(uint8_t id, uint8_t function, uint16_t addr, uint16_t value) {
  uint8_t out[FRAME_LEN] = {id, function, (uint8_t)(addr >> 8), (uint8_t)addr,
                            (uint8_t)(value >> 8), (uint8_t)value, 0, 0};
  uint16_t crc = crc16(out, 6);
  out[6] = crc >> 8;
  out[7] = crc & 0xFF;
  Serial.write(out, FRAME_LEN);
}

// Reads what arrived; answers a whole frame for `id` with a good CRC.
static void modbus8_poll(uint8_t id, Handler handle) {
  // The quiet that ends a partial frame is timed from the last byte read,
  // so it only counts while nothing waits in the receive buffer: a loop
  // busy for longer than 3.5 characters (the light Nano's analogRead and
  // float maths take 304-324 us once the wheel turns) must not cut a frame
  // whose rest arrived meanwhile.
  if (frame_len > 0 && Serial.available() == 0 && micros() - last_byte_us > SILENCE_US)
    frame_len = 0;
  while (Serial.available() > 0) {
    frame[frame_len++] = (uint8_t)Serial.read();
    last_byte_us = micros();
    if (frame_len < FRAME_LEN) continue;
    frame_len = 0;
    uint16_t crc = crc16(frame, 6);
    if (frame[6] != (crc >> 8) || frame[7] != (crc & 0xFF) || frame[0] != id) continue;
    uint8_t function = frame[1];
    uint16_t addr = ((uint16_t)frame[2] << 8) | frame[3];
    uint16_t value = ((uint16_t)frame[4] << 8) | frame[5];
    uint8_t ex = handle(function, addr, &value);
    if (ex) send_frame(id, function | 0x80, addr, ex);
    else send_frame(id, function, addr, value);
  }
}
