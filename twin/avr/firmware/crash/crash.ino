// Crashes on purpose 5 ms after power-up: it calls a function past the end of
// the ATmega328P's 32 KB of flash, where no instruction is.
void setup() {
  Serial.begin(115200);
}

void loop() {
  if (millis() >= 5) {
    void (*nowhere)(void) = (void (*)(void))0x7F00;
    nowhere();
  }
}
