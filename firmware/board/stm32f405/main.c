/* The fingertip board's firmware on an STM32F405: the LSM6DSR on SPI1, tecdar-imu/1 out of USART1.
 * Built with TFW_EMULATED, the register model stands in for the chip (the emulator has none) and the
 * clocks are the emulator's. */
#include "../../core/tfw_app.h"
#include "board.h"

#ifdef TFW_EMULATED
#include <math.h>

#include "../../model/lsm6dsr_model.h"

#define EMULATED_SYSCLK_HZ 168000000u    /* QEMU's netduinoplus2 runs its SysTick at 168 MHz */
static lsm_model chip;
static uint32_t chip_last_us;

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
#define BUS_TRANSFER transfer
#define BUS_CTX (&chip)
#else
#define BUS_TRANSFER board_spi_transfer
#define BUS_CTX 0
#endif

#define POLL_PERIOD_US 100u              /* between FIFO polls the loop only feeds the UART */

static void delay(void *ctx, uint32_t us) {
    (void)ctx;
    board_delay_us(us);
}

static tfw_app app;

int main(void) {
#ifdef TFW_EMULATED
    uint32_t sysclk = EMULATED_SYSCLK_HZ;
    lsm_model_init(&chip);
    chip.signal = signal_at_rest;
#else
    uint32_t sysclk = board_clock_init();
#endif
    board_systick_init(sysclk);
    board_uart_init(sysclk == 168000000u ? 84000000u : sysclk, UART_BAUD);
#ifndef TFW_EMULATED
    board_spi_init();
#endif
    tfw_bus bus = {BUS_TRANSFER, delay, BUS_CTX};
    tfw_app_config cfg = tfw_app_default_config();
    tfw_app_init(&app, &bus, &cfg);
    tfw_app_start(&app, board_now_us());
    uint32_t next_poll = board_now_us();
    for (;;) {
        const uint8_t *p;
        size_t n = tfw_app_tx_peek(&app, &p);
        if (n) {
            tfw_app_tx_done(&app, board_uart_write_some(p, n));
        }
        uint32_t now = board_now_us();
        if ((int32_t)(now - next_poll) >= 0) {
            next_poll = now + POLL_PERIOD_US;
#ifdef TFW_EMULATED
            advance_chip();
#endif
            tfw_app_poll(&app, now);
        }
    }
}
