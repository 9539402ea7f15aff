/*
 * startup.c -- the start-up code the Cortex-M0+ firmwares share (firmware.c: the spindle
 * bench; system.c: the whole system): the vector table, Reset_Handler (copy .data, clear
 * .bss, run the firmware's main) and fw_halt, the address the emulator stops at.
 */

/* The emulator returns here (a breakpoint target); on hardware it is never reached. */
__attribute__((noinline)) void fw_halt(void)
{
    for (;;) {
    }
}

extern unsigned int _sidata, _sdata, _edata, _sbss, _ebss, _estack;
int main(void);
void Reset_Handler(void);
void Default_Handler(void);

void Reset_Handler(void)
{
    unsigned int *src = &_sidata, *dst = &_sdata;
    while (dst < &_edata) *dst++ = *src++;
    for (dst = &_sbss; dst < &_ebss; ++dst) *dst = 0;
    (void)main();
    fw_halt();
}

void Default_Handler(void) { fw_halt(); }

typedef void (*fw_vector)(void);
__attribute__((section(".vectors"), used)) const fw_vector fw_vectors[16] = {
    (fw_vector)(unsigned long)&_estack, Reset_Handler, Default_Handler, Default_Handler,
    0, 0, 0, 0, 0, 0, 0, Default_Handler, 0, 0, Default_Handler, Default_Handler,
};
