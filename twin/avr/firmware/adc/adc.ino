// Reports the battery voltage's ADC reading: for every 'r' received it
// answers "V1 <count>\n" with analogRead(A2), the 10-bit count of the
// battery divider's pin (AVcc reference, 5 V).
void setup() {
  Serial.begin(115200);
}

void loop() {
  if (Serial.available() > 0 && Serial.read() == 'r') {
    Serial.print("V1 ");
    Serial.println(analogRead(A2));
  }
}
