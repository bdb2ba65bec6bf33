/* The firmware's main loop on an STM32F405, whatever is on the sensor bus (board.h). */
#include "board.h"

#define POLL_PERIOD_US 100u              /* between FIFO polls the loop only feeds the UART */

static void delay(void *ctx, uint32_t us) {
    (void)ctx;
    board_delay_us(us);
}

void board_run(tfw_app *app, tfw_transfer_fn transfer, void *bus_ctx, void (*before_poll)(void)) {
    tfw_bus bus = {transfer, delay, bus_ctx};
    tfw_app_config cfg = tfw_app_default_config();
    tfw_app_init(app, &bus, &cfg);
    tfw_app_start(app, board_now_us());
    uint32_t next_poll = board_now_us();
    for (;;) {
        const uint8_t *p;
        size_t n = tfw_app_tx_peek(app, &p);
        if (n) {
            tfw_app_tx_done(app, board_uart_write_some(p, n));
        }
        uint32_t now = board_now_us();
        if ((int32_t)(now - next_poll) >= 0) {
            next_poll = now + POLL_PERIOD_US;
            if (before_poll) {
                before_poll();
            }
            tfw_app_poll(app, now);
        }
    }
}
