// A student's motor node (slave 01) of the Controller_network project's
// 8-byte Modbus line, written as a student would write one from the 8-byte
// Modbus page (docs/protocols/modbus8.md): plain Arduino, Serial, an
// 8-byte receive buffer that starts over after a quiet gap. It is a
// reference "student" for `twin check slave --suite modbus8-slave`,
// outside the twin's own code (not the shipped motor-nano).
//
// Built as it is, it is correct. One define plants a mistake students
// make, so that the checker can be held to finding it and nothing else
// (make BUILD=/tmp/bug DEFINES=-DBUG_CRC_LOW_FIRST student-motor-nano):
//
//   BUG_CRC_LOW_FIRST   its replies' CRC low byte first, as standard
//                       Modbus RTU sends it (this line sends it high byte
//                       first); the requests it checks in the line's order
//
// Wiring (the bench's `motor-nano` map): D2 encoder A (INT0), D3 encoder
// B, D9 PWM to the driver, D10 driver awake, D13 LED. Serial at 115200 8N1.

#define MY_ID 1

const int PWM_PIN = 9, SLEEP_PIN = 10, LED_PIN = 13;

byte frame[8];
int count = 0;
unsigned long lastByteTime = 0;

byte state = 0x80;  // pre-operational
unsigned int setSpeed = 10000;
int rpm = 0;

volatile long pulses = 0;
unsigned long lastRpmTime = 0;

void encoderA() {
  if (digitalRead(3)) pulses--;
  else pulses++;
}

unsigned int crc16(const byte *data, int n) {
  unsigned int crc = 0xFFFF;
  for (int i = 0; i < n; i++) {
    crc ^= data[i];
    for (int b = 0; b < 8; b++) {
      if (crc & 1) crc = (crc >> 1) ^ 0xA001;
      else crc >>= 1;
    }
  }
  return crc;
}

// Puts the CRC of bytes 0-5 into bytes 6-7.
void addCrc(byte *f) {
  unsigned int crc = crc16(f, 6);
#ifdef BUG_CRC_LOW_FIRST
  f[6] = crc & 0xFF;
  f[7] = crc >> 8;
#else
  f[6] = crc >> 8;
  f[7] = crc & 0xFF;
#endif
}

bool crcOk(const byte *f) {
  unsigned int crc = crc16(f, 6);
  return f[6] == (crc >> 8) && f[7] == (crc & 0xFF);
}

void reply(byte function, unsigned int addr, unsigned int value) {
  byte out[8];
  out[0] = MY_ID;
  out[1] = function;
  out[2] = addr >> 8;
  out[3] = addr & 0xFF;
  out[4] = value >> 8;
  out[5] = value & 0xFF;
  addCrc(out);
  Serial.write(out, 8);
}

void handleFrame() {
  if (!crcOk(frame)) return;
  if (frame[0] != MY_ID) return;
  byte function = frame[1];
  unsigned int addr = (frame[2] << 8) | frame[3];
  unsigned int value = (frame[4] << 8) | frame[5];

  // The address first, then the function, then the value.
  if (addr != 0x0001 && addr != 0x0005 && addr != 0x0009) {
    reply(function | 0x80, addr, 2);
    return;
  }
  if (function == 3 && addr == 0x0001) {
    reply(3, addr, state);
  } else if (function == 3 && addr == 0x0005) {
    reply(3, addr, (unsigned int)rpm);
  } else if (function == 6 && addr == 0x0001) {
    if (value != 0x01 && value != 0x02 && value != 0x80 && value != 0x81 && value != 0x82) {
      reply(0x86, addr, 3);
      return;
    }
    reply(6, addr, value);
    state = value;
  } else if (function == 6 && addr == 0x0009) {
    if (value < 21 || value > 12499) {
      reply(0x86, addr, 3);
      return;
    }
    setSpeed = value;
    reply(6, addr, value);
  } else {
    reply(function | 0x80, addr, 1);
  }
}

void readSerial() {
  // A frame cut short: the quiet after its last byte drops it.
  if (count > 0 && Serial.available() == 0 && micros() - lastByteTime > 2000) {
    count = 0;
  }
  while (Serial.available() > 0) {
    frame[count++] = Serial.read();
    lastByteTime = micros();
    if (count == 8) {
      handleFrame();
      count = 0;
    }
  }
}

void drive() {
  if (state == 0x81) state = 0x80;  // init falls to pre-operational
  if (state == 0x82) {               // reset communication
    Serial.flush();
    Serial.end();
    delay(3);
    Serial.begin(115200);
    count = 0;
    state = 0x81;
  }
  bool on = state == 0x01;
  digitalWrite(LED_PIN, on);
  digitalWrite(SLEEP_PIN, on);
  // Open loop: the duty in proportion to the set speed.
  analogWrite(PWM_PIN, on ? (long)setSpeed * 255 / 12500 : 0);
  if (millis() - lastRpmTime >= 20) {
    noInterrupts();
    long n = pulses;
    pulses = 0;
    interrupts();
    // 7 pulses a turn, counted over 20 ms.
    rpm = n * 50 * 60 / 7;
    lastRpmTime = millis();
  }
}

void setup() {
  pinMode(2, INPUT);
  pinMode(3, INPUT);
  pinMode(PWM_PIN, OUTPUT);
  pinMode(SLEEP_PIN, OUTPUT);
  pinMode(LED_PIN, OUTPUT);
  attachInterrupt(0, encoderA, RISING);
  Serial.begin(115200);
}

void loop() {
  readSerial();
  drive();
}
