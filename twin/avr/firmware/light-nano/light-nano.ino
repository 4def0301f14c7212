// The Controller_network project's light-sensor Nano (slave 02), written
// from the 8-byte Modbus protocol page: a photoresistor on A0 sees the
// wheel's marks (three a turn on the bench); every 20 ms the sketch samples
// it (below 3.0 V is dark) and times light-to-dark edges in milliseconds,
// the first one from reset. Register 0006 reads the wheel rpm x 100,
// smoothed over a 5-slot ring.
//
// Pins (wiring map `light-nano`): A0 photoresistor divider, Serial 115200 8N1.

#include "modbus8.h"

static const uint8_t ID = 0x02;
static const uint16_t REG_VALUE = 0x0006;
static const uint32_t SAMPLE_MS = 20;
static const uint32_t EDGE_TIMEOUT_MS = 5000;
static const uint8_t RING = 5;
static const float MARKS = 3.0f;

static float rpm;
static bool dark;
static bool timing = true;   // false after a timeout: the next edge only restarts timing
static uint32_t last_edge_ms, timeout_from_ms, next_sample_ms;
static float ring[RING];
static uint8_t ring_filled, ring_next;

static uint8_t handle(uint8_t function, uint16_t addr, uint16_t *value) {
  if (addr != REG_VALUE) return EX_ADDRESS;
  if (function != FN_READ) return EX_FUNCTION;
  *value = (uint16_t)(rpm * 100.0f);
  return 0;
}

static void sample(uint32_t now) {
  float volts = analogRead(A0) * 5.0f / 1023.0f;
  bool d = volts < 3.0f;
  if (d && !dark) {
    if (timing && now > last_edge_ms) rpm = 60000.0f / (MARKS * (float)(now - last_edge_ms));
    timing = true;
    last_edge_ms = now;
    timeout_from_ms = now;
  }
  dark = d;
  if (now - timeout_from_ms >= EDGE_TIMEOUT_MS) {
    rpm = 0;
    timing = false;
  }
  ring[ring_next] = rpm;
  ring_next = (ring_next + 1) % RING;
  if (ring_filled < RING) ring_filled++;
  if (ring_filled == RING) {
    float sum = 0;
    for (uint8_t i = 0; i < RING; i++) sum += ring[i];
    rpm = 0.3f * rpm + 0.7f * (sum / RING);
  }
}

void setup() {
  Serial.begin(115200);
  next_sample_ms = millis();
}

void loop() {
  modbus8_poll(ID, handle);
  uint32_t now = millis();
  if ((int32_t)(now - next_sample_ms) >= 0) {
    next_sample_ms += SAMPLE_MS;
    sample(now);
  }
}
