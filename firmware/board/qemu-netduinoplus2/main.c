/* The fingertip board's firmware in QEMU's netduinoplus2 (an STM32F405): the MCU support of
 * board/stm32f405/, with the LSM6DSR register model on the bus in place of the chip (the emulator has
 * none) and the emulator's clocks. tecdar-imu/1 goes out of USART1, which QEMU maps to its serial port. */
#include <math.h>

#include "board.h"
#include "lsm6dsr_model.h"

#define EMULATED_SYSCLK_HZ 168000000u    /* QEMU's netduinoplus2 runs its SysTick at 168 MHz */
#define EMULATED_APB2_HZ 84000000u

static lsm_model chip;
static uint32_t chip_last_us;
static tfw_app app;

/* the model's time is the MCU's: samples appear as the microseconds pass */
static void advance_chip(void) {
    uint32_t now = board_now_us();
    int32_t step = (int32_t)(now - chip_last_us);
    if (step > 0) {
        chip_last_us = now;
        lsm_model_advance(&chip, chip.t_ns + (int64_t)step * 1000);
    }
}

static void signal_at_rest(void *ctx, int64_t t_ns, double g[3], double a[3]) {
    (void)ctx;
    double t = (double)t_ns * 1e-9;
    g[0] = 20.0 * sin(6.283185307179586 * 2.0 * t);   /* a slow rocking, so the stream is not constant */
    g[1] = 0.0;
    g[2] = 0.0;
    a[0] = 0.0;
    a[1] = 0.0;
    a[2] = 1.0;
}

static int transfer(void *ctx, const uint8_t *tx, uint8_t *rx, size_t n) {
    advance_chip();
    return lsm_model_transfer(ctx, tx, rx, n);
}

int main(void) {
    lsm_model_init(&chip);
    chip.signal = signal_at_rest;
    board_systick_init(EMULATED_SYSCLK_HZ);
    board_uart_init(EMULATED_APB2_HZ, UART_BAUD);
    board_run(&app, transfer, &chip, advance_chip);
}
