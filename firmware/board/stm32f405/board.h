/* The STM32F405 board: clocks, the microsecond clock, USART1 to the USB-serial bridge, SPI1 to the LSM6DSR. */
#ifndef BOARD_H
#define BOARD_H

#include <stddef.h>
#include <stdint.h>

#include "tfw_app.h"

#ifndef HSE_HZ
#define HSE_HZ 8000000u                  /* the board's crystal; 8 MHz on most F405/F407 boards */
#endif
#ifndef UART_BAUD
#define UART_BAUD 2000000u
#endif

/* 168 MHz from the crystal through the PLL; when the crystal or the PLL does not start, 16 MHz from the
 * internal oscillator (the stream still flows at 2 Mbaud, but the clock is then good to 1 %, not 100 ppm). */
uint32_t board_clock_init(void);
void board_systick_init(uint32_t sysclk_hz);
uint32_t board_now_us(void);
void board_delay_us(uint32_t us);
void board_uart_init(uint32_t apb2_hz, uint32_t baud);
/* as many bytes as the UART takes now without waiting; returns how many */
size_t board_uart_write_some(const uint8_t *data, size_t n);
void board_spi_init(void);
int board_spi_transfer(void *ctx, const uint8_t *tx, uint8_t *rx, size_t n);

/* loop.c: start the firmware on the sensor bus `transfer` (bus_ctx its context) and run it for ever:
 * feed the UART, and poll the FIFO every 100 us, after `before_poll` (NULL: nothing) */
typedef int (*tfw_transfer_fn)(void *ctx, const uint8_t *tx, uint8_t *rx, size_t n);
void board_run(tfw_app *app, tfw_transfer_fn transfer, void *bus_ctx, void (*before_poll)(void));

#endif
