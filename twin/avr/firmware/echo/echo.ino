// UART echo: every byte received is sent back. The baud is given at build
// time (-DECHO_BAUD=9600) so the same sketch checks two line speeds.
#ifndef ECHO_BAUD
#define ECHO_BAUD 115200
#endif

void setup() {
  Serial.begin(ECHO_BAUD);
}

void loop() {
  while (Serial.available() > 0) {
    Serial.write((uint8_t)Serial.read());
  }
}
