// The EV module's controller (the M3CVME tool's MEB slave) as an Arduino
// sketch for an Uno or Nano (ATmega328P, 16 MHz). It serves the module's
// whole I/O map as docs/protocols/meb.md gives it, with the checks in the
// order that page gives, and computes the hall and light-sensor wheel speeds
// as the twin's own controller node does.
//
// Pins (wiring map `ev-controller`):
//   A0 V2, A1 I, A2 V1, A3 LDR      analog inputs through the bench's dividers
//   D2 D3 D4 hall A, B, C           pin-change interrupt, edges timestamped
//   D5 EN, D6 BRK, D7 PRO, D8 DES, D11 CHG   active low, as MEB's SD words
//   D10 FR                          direction: low clockwise, high counter-clockwise
//   D9 VEL                          Timer1 fast PWM, 10 bits, 15.6 kHz; the
//                                   bench's RC filter makes it a voltage
//   D13 LED                         on while the module is enabled
//   Serial 115200 8N1               the RS-485 bus
//
// The ATmega328P has a 10-bit ADC and no DAC: readings are scaled to the
// map's 12-bit counts, and VEL's 12-bit counts to the PWM's 10 bits. The
// battery's state of charge and the drive's trip lines are not wired to
// the board, so FA0 (SOC) reads 0 and no trip is latched here.

#include <avr/interrupt.h>

static const uint8_t SLAVE_ID = 1;
static const uint32_t LOOP_US = 1000;

// Pins.
static const uint8_t PIN_V2 = A0, PIN_I = A1, PIN_V1 = A2, PIN_LDR = A3;
static const uint8_t PIN_EN = 5, PIN_BRK = 6, PIN_PRO = 7, PIN_DES = 8, PIN_FR = 10, PIN_CHG = 11;
static const uint8_t PIN_LED = 13;

// The module: 4 pole pairs, direct drive: 24 hall edges per wheel turn.
static const float EDGES_PER_WHEEL_TURN = 24.0f;
static const uint32_t HALL_TIMEOUT_US = 250000UL;
static const uint32_t STALL_AFTER_US = 500000UL;

// Light detector (twin: LightDetectorConfig::for_sensor, adaptive at power-up).
static const uint16_t LDR_TH_DEFAULT = 1933;
static const uint16_t HYSTERESIS = 10;
static const float ADAPT_DIP_FRACTION = 0.2f;
static const uint16_t ADAPT_MIN_SWING = 200;
static const float TRACKER_STEP = 0.001f / 2.0f;   // loop period / 2 s memory
static const uint32_t NO_DIP_TIMEOUT_US = 2000000UL;

// The register image.
static uint16_t ea[6];          // V2, I, V1, RPM_M, RPM_L, LDR
static uint16_t ed0;            // hall bits, bit 3 dark
static uint16_t fa[2];          // SOC, ERRS
static uint16_t fd0;            // STATUS
struct Settings {
  uint16_t vel, sd0, sd1, ldr_th, rpm_win, ldr_adapt;
};
static Settings stored = {0, 0x1F, 0x01, LDR_TH_DEFAULT, 100, 1};
static Settings applied;

// Hall edges, counted and timestamped by the pin-change interrupt.
static volatile uint32_t hall_edges;
static volatile uint32_t hall_edge_us;
static volatile uint8_t hall_code;

ISR(PCINT2_vect) {
  uint8_t code = (PIND >> 2) & 0x07;
  if (code != hall_code) {
    hall_code = code;
    hall_edges++;
    hall_edge_us = micros();
  }
}

// ---- MEB framing -------------------------------------------------------

static char rx[412];
static uint16_t rx_len;
static bool rx_active;
static char tx[420];

static int hexval(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  return -1;
}
static int decval(char c) { return (c >= '0' && c <= '9') ? c - '0' : -1; }
static bool is_letter(char c) { return (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z'); }
static const char HEX_DIGITS[] = "0123456789ABCDEF";

static void count_drop() {
  if (fa[1] < 0xFFFF) fa[1]++;
}

static uint16_t put_hex2(uint16_t at, uint8_t v) {
  tx[at++] = HEX_DIGITS[v >> 4];
  tx[at++] = HEX_DIGITS[v & 15];
  return at;
}
static uint16_t put_dec2(uint16_t at, uint8_t v) {
  tx[at++] = '0' + v / 10;
  tx[at++] = '0' + v % 10;
  return at;
}
static uint16_t put_word(uint16_t at, uint16_t w) {
  at = put_hex2(at, w >> 8);
  return put_hex2(at, w & 0xFF);
}
static void send_frame(uint16_t len) {
  uint8_t fcs = 0;
  for (uint16_t i = 0; i < len; i++) fcs ^= (uint8_t)tx[i];
  len = put_hex2(len, fcs);
  tx[len++] = '*';
  tx[len++] = '\n';
  Serial.write((const uint8_t *)tx, len);
}
static void send_error(uint8_t addr, uint8_t code) {
  uint16_t n = 0;
  tx[n++] = '@';
  n = put_dec2(n, SLAVE_ID);
  tx[n++] = 'E';
  tx[n++] = 'R';
  n = put_hex2(n, addr);
  n = put_dec2(n, 1);
  n = put_word(n, code);
  send_frame(n);
}

enum Block { EA, ED, SA, SD, VA, VD, FA, FD, NONE };
static Block block_of(char a, char b) {
  if (a == 'E' && b == 'A') return EA;
  if (a == 'E' && b == 'D') return ED;
  if (a == 'S' && b == 'A') return SA;
  if (a == 'S' && b == 'D') return SD;
  if (a == 'V' && b == 'A') return VA;
  if (a == 'V' && b == 'D') return VD;
  if (a == 'F' && b == 'A') return FA;
  if (a == 'F' && b == 'D') return FD;
  return NONE;
}
static const uint8_t BLOCK_SIZE[] = {6, 1, 1, 2, 2, 1, 2, 1};
static bool is_read(Block b) { return b == EA || b == ED || b == FA || b == FD; }

static uint16_t read_word(Block b, uint8_t i) {
  switch (b) {
    case EA: return ea[i];
    case ED: return ed0;
    case FA: return fa[i];
    case FD: return fd0;
    default: return 0;
  }
}

// One frame from '@' to the last byte before '*'; returns false if malformed.
static void serve(const char *f, uint16_t len) {
  // @ ID(2) CMD(2) ADDR(2) CNT(2) DATA(4n) FCS(2)
  if (len < 11) { count_drop(); return; }
  uint8_t fcs = 0;
  for (uint16_t i = 0; i < len - 2; i++) fcs ^= (uint8_t)f[i];
  int f1 = hexval(f[len - 2]), f0 = hexval(f[len - 1]);
  int i1 = decval(f[1]), i0 = decval(f[2]);
  int a1 = hexval(f[5]), a0 = hexval(f[6]);
  int c1 = decval(f[7]), c0 = decval(f[8]);
  if (f1 < 0 || f0 < 0 || i1 < 0 || i0 < 0 || a1 < 0 || a0 < 0 || c1 < 0 || c0 < 0 ||
      !is_letter(f[3]) || !is_letter(f[4]) || (uint8_t)(f1 * 16 + f0) != fcs) {
    count_drop();
    return;
  }
  uint16_t data_chars = len - 11;
  uint8_t id = i1 * 10 + i0, addr = a1 * 16 + a0, cnt = c1 * 10 + c0;
  if (data_chars != 0 && data_chars != 4u * cnt) { count_drop(); return; }
  uint16_t words[99];
  uint8_t nwords = data_chars / 4;
  for (uint8_t w = 0; w < nwords; w++) {
    uint16_t v = 0;
    for (uint8_t k = 0; k < 4; k++) {
      int h = hexval(f[9 + 4 * w + k]);
      if (h < 0) { count_drop(); return; }
      v = v * 16 + h;
    }
    words[w] = v;
  }
  Block b = block_of(f[3], f[4]);
  // Replies are never answered: ER, a read with data, a write acknowledgement.
  if (f[3] == 'E' && f[4] == 'R') return;
  if (b != NONE && is_read(b) && nwords > 0) return;
  if (b != NONE && !is_read(b) && cnt >= 1 && nwords == 0) return;
  bool broadcast = id == 0;
  if (id != SLAVE_ID && !broadcast) return;
  if (b == NONE) { if (!broadcast) send_error(addr, 1); return; }
  if (broadcast && is_read(b)) return;
  if (cnt == 0) { if (!broadcast) send_error(addr, 3); return; }
  if ((uint16_t)addr + cnt > BLOCK_SIZE[b]) { if (!broadcast) send_error(addr, 2); return; }
  uint16_t n = 0;
  if (is_read(b)) {
    tx[n++] = '@';
    n = put_dec2(n, SLAVE_ID);
    tx[n++] = f[3];
    tx[n++] = f[4];
    n = put_hex2(n, addr);
    n = put_dec2(n, cnt);
    for (uint8_t i = 0; i < cnt; i++) n = put_word(n, read_word(b, addr + i));
    send_frame(n);
    return;
  }
  // A write: every value checked, then all stored together or none.
  Settings s = stored;
  bool ok = true;
  for (uint8_t i = 0; i < cnt; i++) {
    uint16_t v = words[i];
    uint8_t at = addr + i;
    switch (b) {
      case SA: ok &= v <= 4095; s.vel = v; break;
      case SD:
        if (at == 0) { ok &= (v & ~0x1F) == 0; s.sd0 = v; }
        else { ok &= (v & ~0x01) == 0; s.sd1 = v; }
        break;
      case VA:
        if (at == 0) { ok &= v <= 4095; s.ldr_th = v; }
        else { ok &= v >= 1 && v <= 1000; s.rpm_win = v; }
        break;
      case VD: ok &= (v & ~1) == 0; s.ldr_adapt = v; break;
      default: break;
    }
  }
  if (!ok) { if (!broadcast) send_error(addr, 3); return; }
  stored = s;
  if (broadcast) return;
  tx[n++] = '@';
  n = put_dec2(n, SLAVE_ID);
  tx[n++] = f[3];
  tx[n++] = f[4];
  n = put_hex2(n, addr);
  n = put_dec2(n, cnt);
  send_frame(n);
}

static void meb_byte(char c) {
  if (c == '@') {
    if (rx_active && rx_len > 0) count_drop();
    rx_active = true;
    rx_len = 0;
    rx[rx_len++] = c;
    return;
  }
  if (!rx_active) return;
  if (c == '\n') {
    rx_active = false;
    uint16_t end = rx_len;
    if (end > 0 && rx[end - 1] == '\r') end--;
    if (end > 0 && rx[end - 1] == '*') serve(rx, end - 1);
    else count_drop();
    return;
  }
  if (rx_len >= 410) {
    rx_active = false;
    count_drop();
    return;
  }
  rx[rx_len++] = c;
}

// ---- the loop: estimators and pins ---------------------------------------

// Hall window estimator (twin: HallRpm).
static bool have_first, have_last;
static uint32_t first_us, first_n, last_us, last_n, seen_edges, window_end_us;
static bool window_started;
static float hall_rpm;

static float hall_tick(uint32_t now) {
  noInterrupts();
  uint32_t edges = hall_edges, edge_us = hall_edge_us;
  interrupts();
  if (edges != seen_edges) {
    if (!have_first) { first_us = edge_us; first_n = edges; have_first = true; }
    last_us = edge_us;
    last_n = edges;
    have_last = true;
  }
  seen_edges = edges;
  uint32_t window = (uint32_t)applied.rpm_win * 1000UL;
  if (!window_started) { window_end_us = now + window; window_started = true; }
  if ((int32_t)(now - window_end_us) >= 0) {
    if (have_first && have_last && last_n > first_n && last_us != first_us) {
      float per_s = (float)(last_n - first_n) / ((float)(last_us - first_us) * 1e-6f);
      hall_rpm = per_s * 60.0f / EDGES_PER_WHEEL_TURN;
    }
    first_us = last_us;
    first_n = last_n;
    have_first = have_last;
    window_end_us = now + window;
  }
  // An edge captured after `now` was read makes a negative interval: it is
  // the newest edge, just in.
  int32_t since = (int32_t)(now - last_us);
  if (since < 0) since = 0;
  if (have_last && (uint32_t)since <= HALL_TIMEOUT_US) {
    if (since > 0) {
      float bound = 60.0f / (EDGES_PER_WHEEL_TURN * (float)since * 1e-6f);
      return hall_rpm < bound ? hall_rpm : bound;
    }
    return hall_rpm;
  }
  hall_rpm = 0;
  have_last = have_first = false;
  return 0;
}

// Light dip estimator (twin: LightRpm).
static bool dark, have_dip, tracked;
static uint32_t last_dip_us;
static float track_high, track_low, light_rpm;

static float light_tick(uint32_t now, uint16_t counts) {
  float x = counts;
  if (!tracked) { track_high = track_low = x; tracked = true; }
  track_high = x > track_high ? x : track_high + (x - track_high) * TRACKER_STEP;
  track_low = x < track_low ? x : track_low + (x - track_low) * TRACKER_STEP;
  bool enter, leave;
  if (applied.ldr_adapt & 1) {
    float swing = track_high - track_low;
    if (swing < ADAPT_MIN_SWING) { enter = false; leave = true; }
    else {
      float dip = ADAPT_DIP_FRACTION * swing;
      enter = x < track_high - dip;
      leave = x > track_high - 0.5f * dip;
    }
  } else {
    enter = counts < applied.ldr_th;
    leave = counts >= applied.ldr_th + HYSTERESIS;
  }
  if (!dark && enter) {
    dark = true;
    if (have_dip && now != last_dip_us) light_rpm = 60.0f / ((float)(now - last_dip_us) * 1e-6f);
    last_dip_us = now;
    have_dip = true;
  } else if (dark && leave) {
    dark = false;
  }
  if (have_dip && now - last_dip_us > NO_DIP_TIMEOUT_US) have_dip = false;
  if (!have_dip) light_rpm = 0;
  // Between dips: at most one turn in the time since the last one (twin:
  // LightRpm), so a slowing wheel reads slower at once.
  if (have_dip && now != last_dip_us) {
    float bound = 60.0f / ((float)(now - last_dip_us) * 1e-6f);
    if (bound < light_rpm) return bound;
  }
  return light_rpm;
}

static uint16_t read12(uint8_t pin) {
  uint32_t v = analogRead(pin);
  return (uint16_t)((v * 4095UL + 511UL) / 1023UL);
}

static uint16_t rpm_word(float rpm) {
  if (rpm < 0) return 0;
  if (rpm > 65535.0f) return 65535;
  return (uint16_t)(rpm + 0.5f);
}

static void set_vel(uint16_t vel) {
  // At either end the pin is held rather than pulsed: fast PWM gives a
  // spike at OCR1A = 0, and simavr does not hold it high at OCR1A = TOP.
  if (vel == 0) {
    TCCR1A &= ~_BV(COM1A1);
    digitalWrite(9, LOW);
  } else if (vel >= 4092) {
    TCCR1A &= ~_BV(COM1A1);
    digitalWrite(9, HIGH);
  } else {
    OCR1A = vel >> 2;
    TCCR1A |= _BV(COM1A1);
  }
}

static uint32_t stalled_since;
static bool stall_timing;

static void tick(uint32_t now) {
  applied = stored;
  ea[0] = read12(PIN_V2);
  ea[1] = read12(PIN_I);
  ea[2] = read12(PIN_V1);
  ea[5] = read12(PIN_LDR);
  float rpm_m = hall_tick(now);
  float rpm_l = light_tick(now, ea[5]);
  ea[3] = rpm_word(rpm_m);
  ea[4] = rpm_word(rpm_l);
  ed0 = (hall_code & 7) | (dark ? 8 : 0);

  uint16_t sd0 = applied.sd0, sd1 = applied.sd1;
  digitalWrite(PIN_EN, sd0 & 1);
  digitalWrite(PIN_BRK, (sd0 >> 1) & 1);
  digitalWrite(PIN_PRO, (sd0 >> 2) & 1);
  digitalWrite(PIN_DES, (sd0 >> 3) & 1);
  digitalWrite(PIN_FR, (sd0 >> 4) & 1);
  digitalWrite(PIN_CHG, sd1 & 1);
  set_vel(applied.vel);
  bool enabled = (sd0 & 1) == 0;
  digitalWrite(PIN_LED, enabled);

  bool stalled = false;
  if (enabled && applied.vel > 0 && ea[3] == 0) {
    if (!stall_timing) { stall_timing = true; stalled_since = now; }
    stalled = now - stalled_since > STALL_AFTER_US;
  } else {
    stall_timing = false;
  }
  fd0 = ((sd0 & 2) == 0 ? 4 : 0) | (stalled ? 8 : 0) | ((sd0 & 16) ? 32 : 0);
}

static uint32_t last_tick_us;

void setup() {
  // Outputs high (off) before they are driven, as at the module's power-up.
  const uint8_t outs[] = {PIN_EN, PIN_BRK, PIN_PRO, PIN_DES, PIN_FR, PIN_CHG};
  for (uint8_t i = 0; i < sizeof(outs); i++) {
    digitalWrite(outs[i], HIGH);
    pinMode(outs[i], OUTPUT);
  }
  pinMode(PIN_LED, OUTPUT);
  pinMode(9, OUTPUT);
  // Timer1: fast PWM, 10 bits (WGM 7), no prescaler: 15.6 kHz on OC1A (D9).
  TCCR1A = _BV(WGM11) | _BV(WGM10);
  TCCR1B = _BV(WGM12) | _BV(CS10);
  set_vel(0);
  // Halls on D2..D4: pin-change interrupts PCINT18..20.
  pinMode(2, INPUT);
  pinMode(3, INPUT);
  pinMode(4, INPUT);
  hall_code = (PIND >> 2) & 0x07;
  PCMSK2 = _BV(PCINT18) | _BV(PCINT19) | _BV(PCINT20);
  PCICR |= _BV(PCIE2);
  Serial.begin(115200);
  applied = stored;
  last_tick_us = micros();
}

void loop() {
  while (Serial.available() > 0) meb_byte((char)Serial.read());
  uint32_t now = micros();
  if (now - last_tick_us >= LOOP_US) {
    last_tick_us += LOOP_US;
    tick(now);
  }
}
