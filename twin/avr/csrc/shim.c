/*
 * The one C file between the twin and Debian's libsimavr (1.6): a small,
 * stable surface that the Rust side calls, so no bindgen (and no libclang)
 * is needed. What it changes from simavr's defaults, and why:
 *
 * - the core never sleeps on the wall clock: the sleep callback is a no-op,
 *   and every run is bounded by a cycle timer at its target, so a sleeping
 *   core stops exactly where the twin's clock is;
 * - the UART prints nothing on stdout and never sleeps on the wall clock
 *   when the firmware polls UCSR0A (simavr's "poll sleep" costs a usleep per
 *   read: tens of microseconds of wall time for every byte a sketch sends);
 *   its bytes are taken with the cycle of the write to UDR0 and timed by the
 *   Rust side from UBRR0/U2X0;
 * - the UART's byte time is the chip's: simavr 1.6 counts a parity bit that
 *   8N1 does not send (11 bits, 93.5 us at 115200), so UDRE came back late
 *   and a sketch's replies left at 93 us a byte instead of the 85 us of a
 *   real ATmega328P; it is set from UBRR0, U2X0 and UCSR0C at every byte;
 * - AVcc and AREF are 5 V (simavr assumes 3.3 V unless told);
 * - every pin of ports B, C and D reports its edges with their cycle, so a
 *   PWM duty is measured from the pin's own edges;
 * - a low level on INT0/INT1 (D2, D3) starts no per-cycle poll while that
 *   interrupt is disabled in EIMSK: simavr 1.6 starts a poll on every cycle
 *   for each low level it is handed in level mode (EICRA's default),
 *   whether or not the interrupt is enabled, so a hall or encoder on D2/D3
 *   read by pin-change interrupts or by polling cost timer callbacks on
 *   every cycle for half the time: most of what the twin cost beyond
 *   simavr itself;
 * - the edges of the pins the twin watches (the wiring map's outputs and
 *   PWM, a VCD trace's pins) are kept with their cycle in a ring the Rust
 *   side drains after each run, for the recording and the trace;
 * - a 16-bit timer's compare register (OCR1A, OCR1B) takes its high byte at
 *   the low byte's write, through the chip's TEMP register: simavr 1.6 lets
 *   the high byte into the register at once and, at the low byte's write,
 *   compares the new value with one whose high byte is already new, so in
 *   fast PWM a write that changes the high byte alone was never applied
 *   (OCR1A from 0x000 to 0x200, VEL 2048 on a 10-bit PWM, left the pin at
 *   the old duty);
 * - a pin a timer drives (OC1A on D9 with COM1A set, and the other compare
 *   outputs) keeps the timer's level when the firmware writes its port:
 *   simavr 1.6 drives every output pin of a port from PORTx at each write
 *   to PORTx, DDRx or PINx, so `digitalWrite(8, ...)` at every pass of
 *   loop() cut each PWM pulse on D9 short (half duty read as 3.6 %), where
 *   the chip's waveform generator overrides PORTx on that pin;
 * - simavr's GDB stub is started only when asked (its run loop polls the
 *   debugger's socket at every instruction), with the core stopped until
 *   the debugger says continue, as `simavr -g` does.
 *
 * SPDX-License-Identifier: GPL-3.0-or-later
 */
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <simavr/sim_avr.h>
#include <simavr/sim_elf.h>
#include <simavr/sim_hex.h>
#include <simavr/sim_irq.h>
#include <simavr/sim_io.h>
#include <simavr/sim_cycle_timers.h>
#include <simavr/avr_uart.h>
#include <simavr/avr_adc.h>
#include <simavr/avr_ioport.h>
#include <simavr/avr_extint.h>
#include <simavr/avr_timer.h>
#include <simavr/sim_gdb.h>

#define TX_RING 512
#define PORTS 3 /* B, C, D */
#define EDGE_RING 16384
#define WIDE_OCRS 8
#define PORT_HOOKS (PORTS * 3) /* PORTx, DDRx and PINx of each port */
#define COMPARE_PINS 8

/* A 16-bit compare register: its high byte waits in TEMP for the low
 * byte's write, which simavr's timer handles. */
typedef struct wide_ocr {
	struct twin_avr *t;
	avr_io_addr_t low, high;
	uint8_t temp;
	avr_io_write_t timer_write;
	void *timer_param;
} wide_ocr_t;

/* A port register's write, wrapped so that the pins a timer drives keep
 * the timer's level. */
typedef struct port_hook {
	struct twin_avr *t;
	int port; /* 0 = B, 1 = C, 2 = D */
	avr_io_write_t write;
	void *param;
} port_hook_t;

/* A timer's compare output: its COMnx bits, and the pin they drive. */
typedef struct compare_pin {
	avr_regbit_t com;
	int index; /* pin index, port B from 0 */
} compare_pin_t;

typedef struct twin_avr {
	avr_t *avr;
	elf_firmware_t *fw;
	uint8_t tx[TX_RING];
	uint64_t tx_cycle[TX_RING];
	uint32_t tx_head, tx_tail;
	uint32_t tx_dropped;
	/* Per pin (port * 8 + bit): level, cycle of its last edge, cycles spent
	 * high before that edge since power-up, and edges seen. */
	uint8_t level[PORTS * 8];
	uint64_t last_edge[PORTS * 8];
	uint64_t high_cycles[PORTS * 8];
	uint64_t edges[PORTS * 8];
	avr_irq_t *uart_in;
	avr_uart_t *uart;
	avr_irq_t *adc[8];
	avr_irq_t *pin_in[PORTS * 8];
	struct pin_ref *refs;
	/* The program counter before the last instruction run: where a crash
	 * happened (simavr moves the PC on when it gives up). */
	uint32_t last_pc;
	/* Pins (bit per index) whose edges go into the ring, with their cycle. */
	uint32_t watch;
	uint64_t edge_cycle[EDGE_RING];
	uint8_t edge_pin[EDGE_RING]; /* index, bit 7 the new level */
	uint32_t edge_head, edge_tail;
	uint32_t edge_dropped;
	wide_ocr_t wide_ocr[WIDE_OCRS];
	port_hook_t port_hook[PORT_HOOKS];
	compare_pin_t compare_pin[COMPARE_PINS];
	int compare_pins;
	/* Pins (bit per index) a timer drives, during a write to their port:
	 * what the port makes of them then is not their level. */
	uint32_t held;
} twin_avr_t;

/* simavr's messages ("Loaded 1638 .text", a crash's reason) would go to
 * stdout, in the middle of the twin's own output: the last one is kept
 * instead, for the error that reports a crash. */
static __thread char last_log[512];
static void keep_log(struct avr_t *avr, const int level, const char *format, va_list ap) {
	(void)avr;
	if (level > LOG_WARNING)
		return;
	/* The message before a crash says why (an invalid opcode and its
	 * address): keep the last two. */
	char line[256];
	vsnprintf(line, sizeof(line), format, ap);
	size_t n = strlen(line);
	while (n && (line[n - 1] == '\n' || line[n - 1] == '\r'))
		line[--n] = 0;
	char *previous = strrchr(last_log, '|');
	const char *keep = previous ? previous + 1 : last_log;
	char joined[1024];
	snprintf(joined, sizeof(joined), "%s|%s", keep, line);
	size_t len = strlen(joined);
	if (len > sizeof(last_log) - 1)
		len = sizeof(last_log) - 1;
	memcpy(last_log, joined, len);
	last_log[len] = 0;
}

const char *twin_avr_last_log(void) { return last_log; }

static void no_sleep(avr_t *avr, avr_cycle_count_t how_long) {
	(void)avr;
	(void)how_long;
}

/* UART0's byte time as the chip has it: start, data, parity if any, stop
 * bits, each 16 (8 with U2X0) times UBRR0 + 1 cycles. */
static void uart_byte_time(twin_avr_t *t) {
	if (!t->uart)
		return;
	const uint8_t *d = t->avr->data;
	uint32_t ubrr = d[0xC4] | ((d[0xC5] & 0x0F) << 8);
	uint32_t bit = (ubrr + 1) * ((d[0xC0] & 0x02) ? 8 : 16);
	uint8_t c = d[0xC2];
	uint32_t data_bits = 5 + ((c >> 1) & 3) + ((d[0xC1] & 0x04) ? 4 : 0);
	if (data_bits > 9)
		data_bits = 9;
	uint32_t bits = 1 + data_bits + (((c >> 4) & 3) ? 1 : 0) + 1 + ((c >> 3) & 1);
	t->uart->cycles_per_byte = (avr_cycle_count_t)bit * bits;
}

static void uart_out(struct avr_irq_t *irq, uint32_t value, void *param) {
	(void)irq;
	twin_avr_t *t = param;
	/* Raised by simavr before it starts its transmit timer for this byte:
	 * the timer then runs at the chip's byte time. */
	uart_byte_time(t);
	uint32_t next = (t->tx_head + 1) % TX_RING;
	if (next == t->tx_tail) {
		t->tx_dropped++;
		return;
	}
	t->tx[t->tx_head] = (uint8_t)value;
	t->tx_cycle[t->tx_head] = t->avr->cycle;
	t->tx_head = next;
}

typedef struct pin_ref {
	twin_avr_t *t;
	int index;
} pin_ref_t;
static pin_ref_t *pin_refs_alloc(twin_avr_t *t) {
	pin_ref_t *refs = calloc(PORTS * 8, sizeof(pin_ref_t));
	for (int i = 0; i < PORTS * 8; i++) {
		refs[i].t = t;
		refs[i].index = i;
	}
	return refs;
}

static void pin_changed(struct avr_irq_t *irq, uint32_t value, void *param) {
	(void)irq;
	pin_ref_t *r = param;
	twin_avr_t *t = r->t;
	uint8_t v = value ? 1 : 0;
	int i = r->index;
	if (v == t->level[i] || (t->held >> i & 1))
		return;
	uint64_t now = t->avr->cycle;
	if (t->level[i])
		t->high_cycles[i] += now - t->last_edge[i];
	t->last_edge[i] = now;
	t->level[i] = v;
	t->edges[i]++;
	if (t->watch >> i & 1) {
		uint32_t next = (t->edge_head + 1) % EDGE_RING;
		if (next == t->edge_tail) {
			t->edge_dropped++;
			return;
		}
		t->edge_cycle[t->edge_head] = now;
		t->edge_pin[t->edge_head] = (uint8_t)(i | (v << 7));
		t->edge_head = next;
	}
}

/* Which pins' edges to keep (bit per pin index, port B from bit 0). */
void twin_avr_watch(twin_avr_t *t, uint32_t pins) { t->watch = pins; }

/* The next edge kept: its cycle, pin index and new level; 0 when none. */
int twin_avr_edge(twin_avr_t *t, uint64_t *cycle, uint8_t *pin, uint8_t *level) {
	if (t->edge_tail == t->edge_head)
		return 0;
	*cycle = t->edge_cycle[t->edge_tail];
	*pin = t->edge_pin[t->edge_tail] & 0x7F;
	*level = t->edge_pin[t->edge_tail] >> 7;
	t->edge_tail = (t->edge_tail + 1) % EDGE_RING;
	return 1;
}

uint32_t twin_avr_edges_dropped(const twin_avr_t *t) { return t->edge_dropped; }

/* Starts simavr's GDB stub on port and stops the core until a debugger
 * connects and continues it. Returns 0, or -1 if the port cannot be
 * listened on. */
int twin_avr_gdb(twin_avr_t *t, int port) {
	t->avr->gdb_port = port;
	if (avr_gdb_init(t->avr) != 0)
		return -1;
	fflush(stdout);
	/* The twin's clock never sleeps on the wall clock; the stub is still
	 * polled at every instruction by simavr's gdb run loop. */
	t->avr->sleep = no_sleep;
	t->avr->state = cpu_Stopped;
	return 0;
}

/* Reads an ELF into a firmware record; NULL if simavr cannot read it. The
 * MCU the ELF names (its .mmcu section, empty for Arduino builds) is copied
 * to mcu. */
void *twin_avr_read_elf(const char *path, char *mcu, size_t mcu_len, uint32_t *frequency) {
	/* Extra room: the record's layout ends with symbols only when simavr
	 * was built with them. */
	avr_global_logger_set(keep_log);
	elf_firmware_t *fw = calloc(1, sizeof(elf_firmware_t) + 1024);
	if (!fw)
		return NULL;
	FILE *f = fopen(path, "rb");
	int first = f ? fgetc(f) : EOF;
	if (f)
		fclose(f);
	if (first == ':') {
		/* Intel HEX, as avr-objcopy and the Arduino IDE write it: flash
		 * only; the MCU and clock come from the node. */
		ihex_chunk_p chunks = NULL;
		int count = read_ihex_chunks(path, &chunks);
		for (int i = 0; i < count; i++) {
			if (chunks[i].baseaddr < 0x800000 && !fw->flash) {
				fw->flash = chunks[i].data;
				fw->flashsize = chunks[i].size;
				fw->flashbase = chunks[i].baseaddr;
				chunks[i].data = NULL;
			}
		}
		for (int i = 0; i < count; i++)
			free(chunks[i].data);
		free(chunks);
		if (!fw->flash) {
			free(fw);
			return NULL;
		}
	} else if (elf_read_firmware(path, fw) != 0) {
		free(fw);
		return NULL;
	}
	if (mcu && mcu_len) {
		strncpy(mcu, fw->mmcu, mcu_len - 1);
		mcu[mcu_len - 1] = 0;
	}
	if (frequency)
		*frequency = fw->frequency;
	return fw;
}

void twin_avr_free_elf(void *fw) { free(fw); }

/* Starts a core for mcu at frequency with the firmware read by
 * twin_avr_read_elf (taken over). NULL if simavr has no such MCU. */
static void ocr_high_write(avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
	(void)avr;
	(void)addr;
	((wide_ocr_t *)param)->temp = v;
}

/* The low byte's write: both bytes at once, as the chip does. simavr's timer
 * applies a new value only if it differs from the register before the
 * write, which it reads from memory: where the high byte changes, the low
 * byte in memory is made to differ first, so the timer sees the change. */
static void ocr_low_write(avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
	wide_ocr_t *w = param;
	if (avr->data[w->high] != w->temp) {
		avr->data[w->high] = w->temp;
		avr->data[addr] = (uint8_t)~v;
	}
	w->timer_write(avr, addr, v, w->timer_param);
}

static void hook_wide_ocrs(twin_avr_t *t) {
	avr_t *avr = t->avr;
	int n = 0;
	for (avr_io_t *io = avr->io_port; io; io = io->next) {
		if (!io->kind || strcmp(io->kind, "timer") != 0)
			continue;
		avr_timer_t *timer = (avr_timer_t *)io;
		for (int c = 0; c < AVR_TIMER_COMP_COUNT && n < WIDE_OCRS; c++) {
			avr_io_addr_t low = timer->comp[c].r_ocr, high = timer->comp[c].r_ocrh;
			if (!low || !high)
				continue;
			int li = AVR_DATA_TO_IO(low), hi = AVR_DATA_TO_IO(high);
			/* Only where the timer watches the low byte and nothing the high. */
			if (!avr->io[li].w.c || avr->io[hi].w.c)
				continue;
			wide_ocr_t *w = &t->wide_ocr[n++];
			*w = (wide_ocr_t){t, low, high, avr->data[high], avr->io[li].w.c, avr->io[li].w.param};
			avr->io[li].w.c = ocr_low_write;
			avr->io[li].w.param = w;
			avr->io[hi].w.c = ocr_high_write;
			avr->io[hi].w.param = w;
		}
	}
}

/* The pins of port `port` a timer's compare output drives now (COMnx set). */
static uint32_t timer_driven(twin_avr_t *t, int port) {
	uint32_t pins = 0;
	for (int i = 0; i < t->compare_pins; i++) {
		compare_pin_t *c = &t->compare_pin[i];
		if (c->index / 8 == port && avr_regbit_get(t->avr, c->com))
			pins |= 1u << c->index;
	}
	return pins;
}

/* A write to PORTx, DDRx or PINx: simavr's, then the pins a timer drives
 * are put back at the timer's level, unseen (the chip never left it). */
static void port_write(avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
	port_hook_t *h = param;
	twin_avr_t *t = h->t;
	uint32_t held = timer_driven(t, h->port);
	t->held = held;
	h->write(avr, addr, v, h->param);
	for (int i = 0; held; i++, held >>= 1)
		if ((held & 1) && t->pin_in[i])
			avr_raise_irq(t->pin_in[i], t->level[i]);
	t->held = 0;
}

static int port_index(char name) {
	return name == 'B' ? 0 : name == 'C' ? 1 : name == 'D' ? 2 : -1;
}

/* Wraps the port registers' writes and finds the timers' compare outputs
 * (after the pins' irqs are known). */
static void hook_ports(twin_avr_t *t) {
	avr_t *avr = t->avr;
	avr_io_addr_t port_reg[PORTS] = {0}; /* PORTB, PORTC, PORTD */
	int n = 0;
	for (avr_io_t *io = avr->io_port; io; io = io->next) {
		if (!io->kind || strcmp(io->kind, "port") != 0)
			continue;
		avr_ioport_t *port = (avr_ioport_t *)io;
		int p = port_index(port->name);
		if (p < 0)
			continue;
		port_reg[p] = port->r_port;
		avr_io_addr_t regs[3] = {port->r_port, port->r_ddr, port->r_pin};
		for (int r = 0; r < 3 && n < PORT_HOOKS; r++) {
			int i = AVR_DATA_TO_IO(regs[r]);
			if (!regs[r] || !avr->io[i].w.c)
				continue;
			port_hook_t *h = &t->port_hook[n++];
			*h = (port_hook_t){t, p, avr->io[i].w.c, avr->io[i].w.param};
			avr->io[i].w.c = port_write;
			avr->io[i].w.param = h;
		}
	}
	for (avr_io_t *io = avr->io_port; io; io = io->next) {
		if (!io->kind || strcmp(io->kind, "timer") != 0)
			continue;
		avr_timer_t *timer = (avr_timer_t *)io;
		for (int c = 0; c < AVR_TIMER_COMP_COUNT && t->compare_pins < COMPARE_PINS; c++) {
			avr_regbit_t com = timer->comp[c].com, pin = timer->comp[c].com_pin;
			if (!com.reg || !pin.reg)
				continue;
			for (int p = 0; p < PORTS; p++)
				if (port_reg[p] == pin.reg)
					t->compare_pin[t->compare_pins++] = (compare_pin_t){com, p * 8 + pin.bit};
		}
	}
}

twin_avr_t *twin_avr_start(void *firmware, const char *mcu, uint32_t frequency) {
	elf_firmware_t *fw = firmware;
	avr_t *avr = avr_make_mcu_by_name(mcu);
	if (!avr) {
		free(fw);
		return NULL;
	}
	twin_avr_t *t = calloc(1, sizeof(twin_avr_t));
	t->avr = avr;
	t->fw = fw;
	avr_init(avr);
	avr->log = 0;
	strncpy(fw->mmcu, mcu, sizeof(fw->mmcu) - 1);
	fw->frequency = frequency;
	fw->vcc = fw->avcc = fw->aref = 5000;
	avr_load_firmware(avr, fw);
	avr->frequency = frequency;
	avr->vcc = avr->avcc = avr->aref = 5000;
	avr->sleep = no_sleep;

	uint32_t flags = 0;
	avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
	flags &= ~(AVR_UART_FLAG_STDIO | AVR_UART_FLAG_POLL_SLEEP);
	avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
	for (avr_io_t *io = avr->io_port; io; io = io->next) {
		if (io->kind && strcmp(io->kind, "uart") == 0 && ((avr_uart_t *)io)->name == '0')
			t->uart = (avr_uart_t *)io;
	}
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
				uart_out, t);
	t->uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
	for (int i = 0; i < 8; i++)
		t->adc[i] = avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0 + i);
	hook_wide_ocrs(t);
	pin_ref_t *refs = pin_refs_alloc(t);
	t->refs = refs;
	const char names[PORTS] = {'B', 'C', 'D'};
	for (int p = 0; p < PORTS; p++) {
		for (int b = 0; b < 8; b++) {
			avr_irq_t *irq = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(names[p]), b);
			t->pin_in[p * 8 + b] = irq;
			if (irq)
				avr_irq_register_notify(irq, pin_changed, &refs[p * 8 + b]);
		}
	}
	hook_ports(t);
	return t;
}

static avr_cycle_count_t stop_here(avr_t *avr, avr_cycle_count_t when, void *param) {
	(void)avr;
	(void)when;
	(void)param;
	return 0;
}

/* Runs the core until its cycle count reaches target, or it stops. Returns
 * simavr's state (cpu_Running, cpu_Sleeping, cpu_Done, cpu_Crashed, ...). */
int twin_avr_run_until(twin_avr_t *t, uint64_t target) {
	avr_t *avr = t->avr;
	if (avr->cycle >= target)
		return avr->state;
	/* A sleeping core jumps to its next timer: this one is at the target. */
	avr_cycle_timer_register(avr, target - avr->cycle, stop_here, t);
	int state = avr->state;
	while (avr->cycle < target) {
		t->last_pc = avr->pc;
		state = avr_run(avr);
		if (state == cpu_Done || state == cpu_Crashed)
			break;
	}
	avr_cycle_timer_cancel(avr, stop_here, t);
	return state;
}

uint64_t twin_avr_cycle(const twin_avr_t *t) { return t->avr->cycle; }
uint32_t twin_avr_pc(const twin_avr_t *t) {
	return t->avr->state == cpu_Crashed ? t->last_pc : t->avr->pc;
}
int twin_avr_state(const twin_avr_t *t) { return t->avr->state; }
uint8_t twin_avr_sreg_i(const twin_avr_t *t) { return t->avr->sreg[S_I]; }

/* A data-space byte (an I/O register such as UBRR0L at 0xC4). */
uint8_t twin_avr_data(const twin_avr_t *t, uint16_t addr) {
	if (addr > t->avr->ramend)
		return 0;
	return t->avr->data[addr];
}

void twin_avr_uart_input(twin_avr_t *t, uint8_t byte) {
	/* simavr paces received bytes into RXC with the same byte time. */
	uart_byte_time(t);
	avr_raise_irq(t->uart_in, byte);
}

/* The next byte the firmware wrote to UDR0 and the cycle it wrote it at;
 * 0 when there is none. */
int twin_avr_uart_output(twin_avr_t *t, uint8_t *byte, uint64_t *cycle) {
	if (t->tx_tail == t->tx_head)
		return 0;
	*byte = t->tx[t->tx_tail];
	*cycle = t->tx_cycle[t->tx_tail];
	t->tx_tail = (t->tx_tail + 1) % TX_RING;
	return 1;
}

uint32_t twin_avr_uart_dropped(const twin_avr_t *t) { return t->tx_dropped; }

void twin_avr_adc(twin_avr_t *t, int channel, uint32_t millivolts) {
	if (channel >= 0 && channel < 8 && t->adc[channel])
		avr_raise_irq(t->adc[channel], millivolts);
}

/* Drives an input pin (port index 0 = B, 1 = C, 2 = D). */
void twin_avr_pin_input(twin_avr_t *t, int pin, int level) {
	if (pin < 0 || pin >= PORTS * 8 || !t->pin_in[pin])
		return;
	int n = pin - (2 * 8 + 2); /* INT0 is PD2, INT1 is PD3 */
	if (!level && (n == 0 || n == 1)) {
		/* simavr 1.6 starts a poll on every cycle for each low level it is
		 * handed in level mode (EICRA's default), enabled or not: keep
		 * that only where the interrupt can fire. */
		int enabled = (t->avr->data[0x3D] >> n) & 1; /* EIMSK */
		avr_extint_set_strict_lvl_trig(t->avr, n, enabled);
	}
	avr_raise_irq(t->pin_in[pin], level ? 1 : 0);
}

/* A pin as the firmware drives it: level, edges since power-up and cycles
 * spent high up to now. */
void twin_avr_pin_output(const twin_avr_t *t, int pin, uint8_t *level, uint64_t *edges,
			 uint64_t *high) {
	if (pin < 0 || pin >= PORTS * 8) {
		*level = 0;
		*edges = 0;
		*high = 0;
		return;
	}
	*level = t->level[pin];
	*edges = t->edges[pin];
	*high = t->high_cycles[pin] + (t->level[pin] ? t->avr->cycle - t->last_edge[pin] : 0);
}

void twin_avr_free(twin_avr_t *t) {
	if (!t)
		return;
	avr_deinit_gdb(t->avr);
	avr_terminate(t->avr);
	free(t->fw);
	free(t->refs);
	free(t);
}
