// Never answers: it opens its serial port and reads every byte, as a sketch
// whose reply never comes (a missing Serial.write, a wrong slave id, a loop
// stuck elsewhere) does on the bench. The twin's watchdog marks it dead.
void setup() {
  Serial.begin(115200);
}

void loop() {
  while (Serial.available() > 0) Serial.read();
}
