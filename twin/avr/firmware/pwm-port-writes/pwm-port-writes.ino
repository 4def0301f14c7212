// D9 driven by Timer1 at half duty (10-bit fast PWM at 15.6 kHz, as the EV
// module's controller sketch sets it), while loop() writes the other pins
// of port B at every pass, as student sketches do: digitalWrite on D8, a
// whole-port write and a pinMode. On the chip, Timer1's waveform output
// overrides PORTB1 while COM1A1 is set, so none of them touches D9's pulse.
void setup() {
  pinMode(9, OUTPUT);
  TCCR1A = _BV(WGM11) | _BV(WGM10);
  TCCR1B = _BV(WGM12) | _BV(CS10);
  OCR1A = 512;
  TCCR1A |= _BV(COM1A1);
}

void loop() {
  digitalWrite(8, HIGH);
  PORTB = 0x00;
  pinMode(10, OUTPUT);
}
