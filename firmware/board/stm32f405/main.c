/* The fingertip board's firmware on an STM32F405: the LSM6DSR on SPI1, tecdar-imu/1 out of USART1.
 * The same MCU under QEMU, with the register model in place of the chip, is board/qemu-netduinoplus2/. */
#include "board.h"

static tfw_app app;

int main(void) {
    uint32_t sysclk = board_clock_init();
    board_systick_init(sysclk);
    board_uart_init(sysclk == 168000000u ? 84000000u : sysclk, UART_BAUD);
    board_spi_init();
    board_run(&app, board_spi_transfer, 0, 0);
}
