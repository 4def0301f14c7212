// A student's MEB slave for the EV module, written as a student of the
// M3CVME lab would write one from the MEB protocol page
// (docs/protocols/meb.md): plain Arduino, Serial, a receive buffer, the
// default map, slave id 01. It is a reference "student" for `twin check
// slave`, outside the twin's own code (not the shipped ev-controller).
//
// Built as it is, it is correct: the meb-slave suite finds nothing. Each
// define below plants one mistake students make, so that the checker can
// be held to finding it and nothing else (one build per define, e.g.
// make BUILD=/tmp/bug DEFINES=-DBUG_ANSWERS_BROADCAST student-meb-slave):
//
//   BUG_FCS_WITHOUT_AT     the replies' FCS leaves out the @
//   BUG_ANSWERS_BAD_FCS    never checks the request's FCS
//   BUG_WRONG_ERROR_CODE   an address out of range gets error 03, not 02
//   BUG_ANSWERS_BROADCAST  takes id 00 for its own, and answers it
//   BUG_NO_RESYNC          does not restart at an @ inside a frame, so a
//                          partial frame spoils the next one
//
// and two that keep every frame right but get the bench wrong, which only
// the bench checks (`twin check slave --bench`) can find:
//
//   BUG_FR_WRONG_PIN       FR on D12, a pin the bench leaves unwired: D10
//                          floats, the module pulls it up, and the motor
//                          always turns counter-clockwise
//   BUG_V1_V2_SWAPPED      V1 read from A0 and V2 from A2: the battery and
//                          the bus swapped
//
// Wiring (the bench's `ev-controller` map): A0 V2, A1 I, A2 V1, A3 LDR;
// D2-D4 hall A-C; D5 EN, D6 BRK, D7 PRO, D8 DES, D10 FR, D11 CHG (active
// low); D9 VEL as PWM through the bench's RC filter. Serial at 115200 8N1
// is the bus. The ADC has 10 bits and the map counts 12: readings are
// scaled, and VEL's 12 bits drive a 10-bit PWM.

#define MY_ID 1

#ifdef BUG_FR_WRONG_PIN
const int EN_PIN = 5, BRK_PIN = 6, PRO_PIN = 7, DES_PIN = 8, FR_PIN = 12, CHG_PIN = 11;
#else
const int EN_PIN = 5, BRK_PIN = 6, PRO_PIN = 7, DES_PIN = 8, FR_PIN = 10, CHG_PIN = 11;
#endif
const int VEL_PIN = 9;  // OC1A: Timer1's PWM
#ifdef BUG_V1_V2_SWAPPED
const int V2_PIN = A2, I_PIN = A1, V1_PIN = A0, LDR_PIN = A3;
#else
const int V2_PIN = A0, I_PIN = A1, V1_PIN = A2, LDR_PIN = A3;
#endif

// Sizes of the blocks, in words.
const int EA_SIZE = 6, ED_SIZE = 1, FA_SIZE = 2, FD_SIZE = 1;
const int SA_SIZE = 1, SD_SIZE = 2, VA_SIZE = 2, VD_SIZE = 1;

// What the master wrote (outputs are active low: all off at power-up).
unsigned int vel = 0;
unsigned int sd[SD_SIZE] = {0x1F, 0x01};
unsigned int va[VA_SIZE] = {1933, 100};
unsigned int vd[VD_SIZE] = {1};
unsigned int errorCount = 0;
// Set by a write: loop() drives the pins only then. (A sketch that drives
// them at every pass works as well: the chip's Timer1 keeps D9's pulse
// whatever port B is written, and twin-avr corrects simavr 1.6, which did
// not.)
bool written = false;

// Hall edges counted in loop(), turned into rpm every half second.
int lastHall = -1;
unsigned long hallEdges = 0;
unsigned long lastRpmTime = 0;
unsigned int rpm = 0;

// The flag's passes in front of the photoresistor (its reading dips below
// a threshold), counted over the same half second: one pass per wheel turn.
// The photoresistor is slow, so at speed the dip is shallow: with LDR_ADAPT
// (VD 00) set, the threshold is midway between the brightest and darkest
// readings of the last half second, if they are far enough apart to be the
// flag; without, it is LDR_TH (VA 00).
unsigned int ldr = 0;
unsigned int ldrHigh = 0, ldrLow = 4095;
unsigned int adaptedTh = 0;  // 0: no flag seen in the last half second
bool inFlag = false;
unsigned long flagPasses = 0;
unsigned int rpmL = 0;

// The frame being received, from @ to before *.
char buf[64];
int len = 0;
bool receiving = false;

char out[64];

int hexDigit(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  return -1;
}

// Reads n hex digits; false if one is not hex.
bool readHex(const char *s, int n, unsigned int *value) {
  *value = 0;
  for (int i = 0; i < n; i++) {
    int d = hexDigit(s[i]);
    if (d < 0) return false;
    *value = *value * 16 + d;
  }
  return true;
}

bool readDec(const char *s, int n, unsigned int *value) {
  *value = 0;
  for (int i = 0; i < n; i++) {
    if (s[i] < '0' || s[i] > '9') return false;
    *value = *value * 10 + (s[i] - '0');
  }
  return true;
}

bool isLetter(char c) {
  return (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z');
}

// The 10-bit ADC's reading as the map's 12-bit counts, rounded.
unsigned int read12(int pin) {
  unsigned long v = analogRead(pin);
  return (v * 4095 + 511) / 1023;
}

unsigned char fcs(const char *s, int n) {
  unsigned char x = 0;
  for (int i = 0; i < n; i++) x ^= s[i];
  return x;
}

// Sends out[0..n) with its FCS and *\n.
void sendReply(int n) {
#ifdef BUG_FCS_WITHOUT_AT
  unsigned char check = fcs(out + 1, n - 1);
#else
  unsigned char check = fcs(out, n);
#endif
  sprintf(out + n, "%02X*\n", check);
  Serial.print(out);
}

void sendError(unsigned int addr, int code) {
  int n = sprintf(out, "@%02dER%02X01%04X", MY_ID, addr, code);
  sendReply(n);
}

unsigned int readWord(const char *cmd, unsigned int a) {
  if (cmd[0] == 'E' && cmd[1] == 'A') {
    switch (a) {
      case 0: return read12(V2_PIN);
      case 1: return read12(I_PIN);
      case 2: return read12(V1_PIN);
      case 3: return rpm;
      case 4: return rpmL;
      default: return ldr;
    }
  }
  if (cmd[0] == 'E') {
    unsigned int hall = digitalRead(2) | (digitalRead(3) << 1) | (digitalRead(4) << 2);
    unsigned int dark = (unsigned int)analogRead(A3) * 4 > va[0] ? 8 : 0;
    return hall | dark;
  }
  if (cmd[0] == 'F' && cmd[1] == 'A') return a == 0 ? 0 : errorCount;
  // FD0: bit 2 brake applied (BRK low), bit 5 counter-clockwise (FR high).
  unsigned int status = 0;
  if ((sd[0] & 2) == 0) status |= 4;
  if (sd[0] & 16) status |= 32;
  return status;
}

// The size of a command's block, 0 for a command not in the table.
int blockSize(const char *cmd) {
  if (cmd[0] == 'E' && cmd[1] == 'A') return EA_SIZE;
  if (cmd[0] == 'E' && cmd[1] == 'D') return ED_SIZE;
  if (cmd[0] == 'F' && cmd[1] == 'A') return FA_SIZE;
  if (cmd[0] == 'F' && cmd[1] == 'D') return FD_SIZE;
  if (cmd[0] == 'S' && cmd[1] == 'A') return SA_SIZE;
  if (cmd[0] == 'S' && cmd[1] == 'D') return SD_SIZE;
  if (cmd[0] == 'V' && cmd[1] == 'A') return VA_SIZE;
  if (cmd[0] == 'V' && cmd[1] == 'D') return VD_SIZE;
  return 0;
}

bool isRead(const char *cmd) {
  return cmd[0] == 'E' || cmd[0] == 'F';
}

// Whether value v may be written at address a of the block.
bool valueOk(const char *cmd, unsigned int a, unsigned int v) {
  if (cmd[0] == 'S' && cmd[1] == 'A') return v <= 4095;
  if (cmd[0] == 'S') return (v & ~(a == 0 ? 0x1F : 0x01)) == 0;
  if (cmd[1] == 'A') return a == 0 ? v <= 4095 : (v >= 1 && v <= 1000);
  return (v & ~1) == 0;
}

void store(const char *cmd, unsigned int a, unsigned int v) {
  if (cmd[0] == 'S' && cmd[1] == 'A') vel = v;
  else if (cmd[0] == 'S') sd[a] = v;
  else if (cmd[1] == 'A') va[a] = v;
  else vd[a] = v;
  written = true;
}

// One frame, from @ to before *: answered, or ignored.
void handleFrame() {
  if (len < 11 || (len - 11) % 4 != 0) {
    errorCount++;
    return;
  }
  unsigned int id, addr, count, given;
  char cmd[2] = {buf[3], buf[4]};
  if (!readDec(buf + 1, 2, &id) || !isLetter(cmd[0]) || !isLetter(cmd[1]) ||
      !readHex(buf + 5, 2, &addr) || !readDec(buf + 7, 2, &count) ||
      !readHex(buf + len - 2, 2, &given)) {
    errorCount++;
    return;
  }
  int words = (len - 11) / 4;
  unsigned int data[8];
  if (words > 8) {
    errorCount++;
    return;
  }
  for (int i = 0; i < words; i++) {
    if (!readHex(buf + 9 + 4 * i, 4, &data[i])) {
      errorCount++;
      return;
    }
  }
#ifndef BUG_ANSWERS_BAD_FCS
  if (fcs(buf, len - 2) != given) {
    errorCount++;
    return;
  }
#endif
  if (words != 0 && words != (int)count) {
    errorCount++;
    return;
  }
#ifdef BUG_ANSWERS_BROADCAST
  if (id == 0) id = MY_ID;
#endif
  if (id != MY_ID && id != 0) return;

  int size = blockSize(cmd);
  // Frames shaped like replies are other slaves' (or my own echo): silence.
  if (cmd[0] == 'E' && cmd[1] == 'R') return;
  if (size > 0 && isRead(cmd) && words > 0) return;
  if (size > 0 && !isRead(cmd) && count > 0 && words == 0) return;

  bool broadcast = id == 0;
  if (broadcast && (size == 0 || isRead(cmd))) return;

  if (size == 0) {
    if (!broadcast) sendError(addr, 1);
    return;
  }
  if (count == 0) {
    if (!broadcast) sendError(addr, 3);
    return;
  }
  if (addr + count > (unsigned int)size) {
#ifdef BUG_WRONG_ERROR_CODE
    if (!broadcast) sendError(addr, 3);
#else
    if (!broadcast) sendError(addr, 2);
#endif
    return;
  }
  int n = sprintf(out, "@%02d%c%c%02X%02d", MY_ID, cmd[0], cmd[1], addr, count);
  if (isRead(cmd)) {
    for (unsigned int i = 0; i < count; i++) {
      n += sprintf(out + n, "%04X", readWord(cmd, addr + i));
    }
    sendReply(n);
    return;
  }
  for (int i = 0; i < words; i++) {
    if (!valueOk(cmd, addr + i, data[i])) {
      if (!broadcast) sendError(addr, 3);
      return;
    }
  }
  for (int i = 0; i < words; i++) store(cmd, addr + i, data[i]);
  if (!broadcast) sendReply(n);
}

void receive(char c) {
#ifdef BUG_NO_RESYNC
  if (c == '@' && !receiving) {
#else
  if (c == '@') {
#endif
    receiving = true;
    len = 0;
  }
  if (!receiving) return;  // noise between frames
  if (c == '\n') {
    receiving = false;
    if (len > 0 && buf[len - 1] == '\r') len--;
    if (len > 0 && buf[len - 1] == '*') {
      len--;
      handleFrame();
    } else {
      errorCount++;
    }
    return;
  }
  if (len >= (int)sizeof(buf)) {  // too long for any frame of mine
    receiving = false;
    errorCount++;
    return;
  }
  buf[len++] = c;
}

// VEL's 12 bits on Timer1's 10-bit fast PWM (15.6 kHz): analogWrite's
// 490 Hz and 8 bits would ripple through the bench's 1 ms RC filter.
// At 0 the pin is held low (fast PWM still pulses once per period).
void setVel(unsigned int v) {
  if (v == 0) {
    TCCR1A &= ~_BV(COM1A1);
    digitalWrite(VEL_PIN, LOW);
  } else {
    OCR1A = v >> 2;
    TCCR1A |= _BV(COM1A1);
  }
}

void setOutputs() {
  digitalWrite(EN_PIN, sd[0] & 1);
  digitalWrite(BRK_PIN, (sd[0] >> 1) & 1);
  digitalWrite(PRO_PIN, (sd[0] >> 2) & 1);
  digitalWrite(DES_PIN, (sd[0] >> 3) & 1);
  digitalWrite(FR_PIN, (sd[0] >> 4) & 1);
  digitalWrite(CHG_PIN, sd[1] & 1);
  setVel(vel);
}

void countHall() {
  int hall = digitalRead(2) | (digitalRead(3) << 1) | (digitalRead(4) << 2);
  if (hall != lastHall) {
    if (lastHall >= 0) hallEdges++;
    lastHall = hall;
  }
  ldr = read12(LDR_PIN);
  if (ldr > ldrHigh) ldrHigh = ldr;
  if (ldr < ldrLow) ldrLow = ldr;
  unsigned int th = vd[0] ? adaptedTh : va[0];
  if (!inFlag && ldr < th) {
    inFlag = true;
    flagPasses++;
  } else if (inFlag && ldr >= th + 10) {
    inFlag = false;
  }
  if (millis() - lastRpmTime >= 500) {
    // 24 hall edges per wheel turn, counted over half a second.
    rpm = hallEdges * 60 * 2 / 24;
    hallEdges = 0;
    rpmL = flagPasses * 60 * 2;
    flagPasses = 0;
    adaptedTh = ldrHigh - ldrLow >= 200 ? (ldrHigh + ldrLow) / 2 : 0;
    ldrHigh = 0;
    ldrLow = 4095;
    lastRpmTime = millis();
  }
}

void setup() {
  pinMode(EN_PIN, OUTPUT);
  pinMode(BRK_PIN, OUTPUT);
  pinMode(PRO_PIN, OUTPUT);
  pinMode(DES_PIN, OUTPUT);
  pinMode(FR_PIN, OUTPUT);
  pinMode(CHG_PIN, OUTPUT);
  pinMode(VEL_PIN, OUTPUT);
  pinMode(2, INPUT);
  pinMode(3, INPUT);
  pinMode(4, INPUT);
  // Timer1: fast PWM, 10 bits (TOP 0x3FF), no prescaler.
  TCCR1A = _BV(WGM11) | _BV(WGM10);
  TCCR1B = _BV(WGM12) | _BV(CS10);
  setOutputs();
  Serial.begin(115200);
}

void loop() {
  while (Serial.available() > 0) {
    receive(Serial.read());
  }
  if (written) {
    written = false;
    setOutputs();
  }
  countHall();
}
