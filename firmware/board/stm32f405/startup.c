/* Cortex-M4 start-up for the STM32F405: the vector table, .data and .bss, the FPU, then main. */
#include <stdint.h>

extern uint32_t _stack_top, _data_load, _data_start, _data_end, _bss_start, _bss_end;
int main(void);
void reset_handler(void);
void systick_handler(void);

#define SCB_CPACR (*(volatile uint32_t *)0xE000ED88u)

static void default_handler(void) {
    for (;;) {
    }
}

void reset_handler(void) {
    uint32_t *src = &_data_load, *dst = &_data_start;
    while (dst < &_data_end) {
        *dst++ = *src++;
    }
    for (dst = &_bss_start; dst < &_bss_end;) {
        *dst++ = 0;
    }
    SCB_CPACR |= 0xFu << 20;                 /* CP10, CP11: full access to the FPU */
    __asm volatile("dsb\n isb");
    main();
    for (;;) {
    }
}

/* the core's 16 exceptions (the initial stack pointer first); the firmware polls its peripherals and uses no
 * device interrupts */
__attribute__((section(".isr_vector"), used)) static const uintptr_t vectors[16] = {
    (uintptr_t)&_stack_top, (uintptr_t)reset_handler, (uintptr_t)default_handler, (uintptr_t)default_handler,
    (uintptr_t)default_handler, (uintptr_t)default_handler, (uintptr_t)default_handler, 0, 0, 0, 0,
    (uintptr_t)default_handler, (uintptr_t)default_handler, 0, (uintptr_t)default_handler,
    (uintptr_t)systick_handler,
};
