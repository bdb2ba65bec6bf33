/* The STM32F405 board (RM0090 register addresses; no vendor headers): clocks, SysTick, USART1, SPI1. */
#include "board.h"

#define REG(addr) (*(volatile uint32_t *)(addr))

#define RCC_BASE 0x40023800u
#define RCC_CR REG(RCC_BASE + 0x00u)
#define RCC_PLLCFGR REG(RCC_BASE + 0x04u)
#define RCC_CFGR REG(RCC_BASE + 0x08u)
#define RCC_AHB1ENR REG(RCC_BASE + 0x30u)
#define RCC_APB2ENR REG(RCC_BASE + 0x44u)
#define FLASH_ACR REG(0x40023C00u)
#define GPIOA_BASE 0x40020000u
#define GPIOA_MODER REG(GPIOA_BASE + 0x00u)
#define GPIOA_OSPEEDR REG(GPIOA_BASE + 0x08u)
#define GPIOA_BSRR REG(GPIOA_BASE + 0x18u)
#define GPIOA_AFRL REG(GPIOA_BASE + 0x20u)
#define GPIOA_AFRH REG(GPIOA_BASE + 0x24u)
#define USART1_BASE 0x40011000u
#define USART1_SR REG(USART1_BASE + 0x00u)
#define USART1_DR REG(USART1_BASE + 0x04u)
#define USART1_BRR REG(USART1_BASE + 0x08u)
#define USART1_CR1 REG(USART1_BASE + 0x0Cu)
#define SPI1_BASE 0x40013000u
#define SPI1_CR1 REG(SPI1_BASE + 0x00u)
#define SPI1_SR REG(SPI1_BASE + 0x08u)
#define SPI1_DR REG(SPI1_BASE + 0x0Cu)
#define SYST_CSR REG(0xE000E010u)
#define SYST_RVR REG(0xE000E014u)
#define SYST_CVR REG(0xE000E018u)
#define SCB_ICSR REG(0xE000ED04u)
#define ICSR_PENDSTSET (1u << 26)

#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_PLLON (1u << 24)
#define RCC_CR_PLLRDY (1u << 25)
#define CLOCK_WAIT_POLLS 200000u         /* a few ms at 16 MHz: a crystal starts in about 2 ms */
#define USART_SR_TXE (1u << 7)
#define SPI_SR_RXNE (1u << 0)
#define SPI_SR_TXE (1u << 1)
#define SPI_SR_BSY (1u << 7)
#define SPI_POLLS 10000u
#define CS_PIN 4u                        /* PA4 */

static volatile uint32_t ms_count;
static uint32_t ticks_per_ms;

void systick_handler(void) { ms_count++; }

static int wait_set(volatile uint32_t *reg, uint32_t bit) {
    for (uint32_t i = 0; i < CLOCK_WAIT_POLLS; i++) {
        if (*reg & bit) {
            return 1;
        }
    }
    return 0;
}

uint32_t board_clock_init(void) {
    RCC_CR |= RCC_CR_HSEON;
    if (!wait_set(&RCC_CR, RCC_CR_HSERDY)) {
        return 16000000u;                /* no crystal: stay on the 16 MHz HSI */
    }
    /* PLL: VCO in = HSE / M = 1 MHz, VCO = x336, SYSCLK = /2 = 168 MHz, USB = /7 = 48 MHz */
    uint32_t m = HSE_HZ / 1000000u;
    RCC_PLLCFGR = m | (336u << 6) | (0u << 16) | (1u << 22) | (7u << 24);
    RCC_CR |= RCC_CR_PLLON;
    if (!wait_set(&RCC_CR, RCC_CR_PLLRDY)) {
        return 16000000u;
    }
    FLASH_ACR = 5u | (1u << 8) | (1u << 9) | (1u << 10);   /* 5 wait states at 168 MHz, prefetch, caches */
    RCC_CFGR = (RCC_CFGR & ~0xFCF3u) | (0x5u << 10) | (0x4u << 13) | 0x2u;   /* APB1 /4, APB2 /2, PLL */
    for (uint32_t i = 0; i < CLOCK_WAIT_POLLS && (RCC_CFGR & 0xCu) != 0x8u; i++) {
    }
    return (RCC_CFGR & 0xCu) == 0x8u ? 168000000u : 16000000u;
}

void board_systick_init(uint32_t sysclk_hz) {
    ticks_per_ms = sysclk_hz / 1000u;
    SYST_RVR = ticks_per_ms - 1u;
    SYST_CVR = 0;
    SYST_CSR = 0x7u;                     /* processor clock, interrupt, enable */
}

uint32_t board_now_us(void) {
    uint32_t ms, val, pending;
    do {                                 /* a millisecond tick between the reads: read again */
        ms = ms_count;
        val = SYST_CVR;
        pending = SCB_ICSR & ICSR_PENDSTSET;
    } while (ms != ms_count);
    if (pending && val > ticks_per_ms / 2u) {
        ms++;                            /* the counter reloaded but its interrupt has not run yet */
    }
    return ms * 1000u + (ticks_per_ms - 1u - val) / (ticks_per_ms / 1000u);
}

void board_delay_us(uint32_t us) {
    uint32_t t0 = board_now_us();
    while ((uint32_t)(board_now_us() - t0) < us) {
    }
}

void board_uart_init(uint32_t apb2_hz, uint32_t baud) {
    RCC_AHB1ENR |= 1u << 0;              /* GPIOA */
    RCC_APB2ENR |= 1u << 4;              /* USART1 */
    GPIOA_MODER = (GPIOA_MODER & ~(0xFu << 18)) | (0xAu << 18);        /* PA9, PA10: alternate function */
    GPIOA_AFRH = (GPIOA_AFRH & ~(0xFFu << 4)) | (0x77u << 4);          /* AF7: USART1 */
    GPIOA_OSPEEDR |= 0xFu << 18;
    /* 8x oversampling, so that 2 Mbaud is reachable from 16 MHz too: the divider in eighths,
     * 84 MHz / 2 Mbaud = 42 = 5 + 2/8 (exact); 16 MHz / 2 Mbaud = 8 = 1 + 0/8 */
    uint32_t eighths = (apb2_hz + baud / 2u) / baud;
    USART1_BRR = ((eighths / 8u) << 4) | (eighths % 8u);
    USART1_CR1 = (1u << 15) | (1u << 13) | (1u << 3);   /* OVER8, UE, TE */
}

size_t board_uart_write_some(const uint8_t *data, size_t n) {
    size_t i = 0;
    while (i < n && (USART1_SR & USART_SR_TXE)) {
        USART1_DR = data[i++];
    }
    return i;
}

void board_spi_init(void) {
    RCC_AHB1ENR |= 1u << 0;
    RCC_APB2ENR |= 1u << 12;             /* SPI1 */
    GPIOA_BSRR = 1u << CS_PIN;           /* CS high before it is an output */
    GPIOA_MODER = (GPIOA_MODER & ~(0xFFu << 8)) | (0x1u << 8) | (0xA8u << 8);   /* PA4 out, PA5-7 AF */
    GPIOA_AFRL = (GPIOA_AFRL & ~(0xFFF0u << 16)) | (0x5550u << 16);            /* AF5: SPI1 */
    GPIOA_OSPEEDR |= 0xFFu << 8;
    /* master, mode 3 (CPOL 1, CPHA 1), APB2 / 16 = 5.25 MHz (the chip's SPI is 10 MHz at most), software CS */
    SPI1_CR1 = (1u << 2) | (1u << 1) | (1u << 0) | (3u << 3) | (1u << 9) | (1u << 8) | (1u << 6);
}

int board_spi_transfer(void *ctx, const uint8_t *tx, uint8_t *rx, size_t n) {
    (void)ctx;
    int rc = 0;
    GPIOA_BSRR = 1u << (CS_PIN + 16u);   /* CS low */
    for (size_t i = 0; i < n && rc == 0; i++) {
        uint32_t polls = 0;
        while (!(SPI1_SR & SPI_SR_TXE) && ++polls < SPI_POLLS) {
        }
        SPI1_DR = tx[i];
        polls = 0;
        while (!(SPI1_SR & SPI_SR_RXNE) && ++polls < SPI_POLLS) {
        }
        if (polls >= SPI_POLLS) {
            rc = -1;                     /* the peripheral is stuck: a bus error, not a hang */
        }
        rx[i] = (uint8_t)SPI1_DR;
    }
    for (uint32_t polls = 0; (SPI1_SR & SPI_SR_BSY) && polls < SPI_POLLS; polls++) {
    }
    GPIOA_BSRR = 1u << CS_PIN;           /* CS high */
    return rc;
}
