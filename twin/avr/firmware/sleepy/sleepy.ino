// Goes to sleep with interrupts off 2 ms after power-up: nothing can ever
// wake it, as on a real board.
#include <avr/sleep.h>

void setup() {}

void loop() {
  if (millis() >= 2) {
    cli();
    set_sleep_mode(SLEEP_MODE_PWR_DOWN);
    sleep_enable();
    sleep_cpu();
  }
}
