// The Controller_network motor Nano's pinout and registers (as
// motor-nano), with the receive routine student sketches often have: when a
// byte has come, read eight with Serial.readBytes and its default 1 s
// timeout, and answer if they make a frame. Nothing resynchronises on a
// gap: a frame whose first bytes were lost (sent before Serial.begin)
// leaves its last bytes to begin the next "frame", and a master that sends
// again within the timeout keeps every later frame misaligned. A test
// sketch, written for the twin's tests and its firmware chapter: it shows
// what a board that boots after its master costs such a sketch.
//
// Pins (wiring map `motor-nano`):
//   D2 (INT0, rising)  encoder channel A: counts up, down while B is high
//   D3                 encoder channel B: direction
//   D4                 driver fault input: must read high
//   D9                 software PWM, toggled from Timer1 every 100 us
//   D10                driver sleep: high = awake (operational only)
//   D13                LED: on in operational
//   Serial 115200 8N1  the line to the master

// The frame, its CRC and the reply are the motor sketch's own; only the
// receive routine (loop) differs, so the header's resynchronising
// receiver, modbus8_poll, goes unused here on purpose.
#pragma GCC diagnostic ignored "-Wunused-function"
#include "../motor-nano/modbus8.h"

static const uint8_t ID = 0x01;
static const uint16_t REG_STATE = 0x0001, REG_RPM = 0x0005, REG_SET_SPEED = 0x0009;
static const uint8_t ST_OPERATIONAL = 0x01, ST_STOPPED = 0x02, ST_PREOP = 0x80,
                     ST_INIT = 0x81, ST_RESET_COMM = 0x82;
static const uint8_t PIN_A = 2, PIN_B = 3, PIN_FAULT = 4, PIN_PWM = 9, PIN_SLEEP = 10, PIN_LED = 13;
static const uint8_t PULSES = 7;
static const float KP = 0.27f, TI = 0.41f, OUT_MIN = 1.0f, OUT_MAX = 12500.0f;

static uint8_t state = ST_PREOP;
static uint16_t set_point = 10000;
static int16_t latched_rpm;
static float integral;

static volatile int32_t encoder_count;
static int32_t window_start;
static uint32_t next_latch_ms, next_pi_ms, fault_low_since_ms;
static bool fault_low, pi_due;

// Software PWM: 100 steps of 100 us make the 10 ms period.
static volatile uint8_t duty_percent;
static volatile uint8_t pwm_step;

ISR(TIMER1_COMPA_vect) {
  if (++pwm_step >= 100) pwm_step = 0;
  if (pwm_step < duty_percent) PORTB |= _BV(PB1);
  else PORTB &= ~_BV(PB1);
}

static void encoder_a_rising() {
  if (PIND & _BV(PD3)) encoder_count--;
  else encoder_count++;
}

static uint8_t handle(uint8_t function, uint16_t addr, uint16_t *value) {
  if (addr != REG_STATE && addr != REG_RPM && addr != REG_SET_SPEED) return EX_ADDRESS;
  bool readable = addr != REG_SET_SPEED, writable = addr != REG_RPM;
  if (function == FN_READ && readable) {
    *value = addr == REG_STATE ? state : (uint16_t)latched_rpm;
    return 0;
  }
  if (function != FN_WRITE || !writable) return EX_FUNCTION;
  if (addr == REG_STATE) {
    uint16_t v = *value;
    if (v != ST_OPERATIONAL && v != ST_STOPPED && v != ST_PREOP && v != ST_INIT && v != ST_RESET_COMM)
      return EX_VALUE;
    state = (uint8_t)v;
  } else {
    if (*value < 21 || *value > 12499) return EX_VALUE;
    set_point = *value;
  }
  return 0;
}

static int32_t count_now() {
  noInterrupts();
  int32_t c = encoder_count;
  interrupts();
  return c;
}

static void run_pi() {
  float sp = set_point;
  float error = sp - latched_rpm;
  float next = integral + error * 0.1f;
  float out = KP * (error + next / TI);
  float clamped = constrain(out, OUT_MIN, OUT_MAX);
  bool winding = (out > OUT_MAX && error > 0) || (out < OUT_MIN && error < 0);
  if (!winding) integral = next;
  duty_percent = (uint8_t)(constrain(clamped / sp, 0.01f, 0.99f) * 100.0f);
}

void setup() {
  pinMode(PIN_A, INPUT);
  pinMode(PIN_B, INPUT);
  pinMode(PIN_FAULT, INPUT);
  pinMode(PIN_PWM, OUTPUT);
  pinMode(PIN_SLEEP, OUTPUT);
  pinMode(PIN_LED, OUTPUT);
  digitalWrite(PIN_SLEEP, LOW);
  attachInterrupt(digitalPinToInterrupt(PIN_A), encoder_a_rising, RISING);
  // Timer1 in CTC mode, no prescaler: a compare match every 1600 cycles.
  TCCR1A = 0;
  TCCR1B = _BV(WGM12) | _BV(CS10);
  OCR1A = 1599;
  TIMSK1 = _BV(OCIE1A);
  Serial.begin(115200);
  uint32_t now = millis();
  window_start = count_now();
  next_latch_ms = now + 20;
  next_pi_ms = now + 100;
}

// The naive receive: eight bytes from the first one that came, however
// long they take (up to the 1 s timeout) and whatever they were.
static uint8_t buf[FRAME_LEN];

static void receive() {
  if (Serial.available() > 0) {
    Serial.readBytes(buf, FRAME_LEN);
    uint16_t crc = crc16(buf, 6);
    if (buf[6] != (crc >> 8) || buf[7] != (crc & 0xFF) || buf[0] != ID) return;
    uint8_t function = buf[1];
    uint16_t addr = ((uint16_t)buf[2] << 8) | buf[3];
    uint16_t value = ((uint16_t)buf[4] << 8) | buf[5];
    uint8_t ex = handle(function, addr, &value);
    if (ex) send_frame(ID, function | 0x80, addr, ex);
    else send_frame(ID, function, addr, value);
  }
}

void loop() {
  receive();
  uint32_t now = millis();
  if ((int32_t)(now - next_latch_ms) >= 0) {
    int32_t c = count_now();
    // rpm = count per 20 ms / pulses x 60 s, truncated to 16 bits: steps of 428.57 rpm.
    latched_rpm = (int16_t)((float)(c - window_start) * 50.0f / PULSES * 60.0f);
    window_start = c;
    next_latch_ms += 20;
  }
  if ((int32_t)(now - next_pi_ms) >= 0) {
    pi_due = true;
    next_pi_ms += 100;
  }
  // The driver's fault line held low for over 5 ms stops the motor.
  if (digitalRead(PIN_FAULT) == LOW) {
    if (!fault_low) fault_low_since_ms = now;
    fault_low = true;
  } else {
    fault_low = false;
  }
  bool fault = fault_low && now - fault_low_since_ms > 5;
  switch (state) {
    case ST_INIT: state = ST_PREOP; break;
    case ST_RESET_COMM:
      Serial.end();
      delay(3);
      Serial.begin(115200);
      state = ST_INIT;
      break;
    case ST_PREOP: if (fault) state = ST_STOPPED; break;
    case ST_OPERATIONAL:
      if (fault) state = ST_STOPPED;
      else if (pi_due) { pi_due = false; run_pi(); }
      break;
    default: break;
  }
  bool on = state == ST_OPERATIONAL;
  digitalWrite(PIN_LED, on ? HIGH : LOW);
  digitalWrite(PIN_SLEEP, on ? HIGH : LOW);
}
