/* A small test runner: CHECK records a failure with its line and goes on; each TEST is a function. */
#ifndef UNIT_H
#define UNIT_H

#include <stdio.h>

static int unit_failures, unit_checks;

#define CHECK(cond)                                                                  \
    do {                                                                             \
        unit_checks++;                                                               \
        if (!(cond)) {                                                               \
            unit_failures++;                                                         \
            fprintf(stderr, "%s:%d: %s: CHECK(%s) failed\n", __FILE__, __LINE__, __func__, #cond); \
        }                                                                            \
    } while (0)

#define CHECK_EQ(a, b)                                                               \
    do {                                                                             \
        long long unit_a = (long long)(a), unit_b = (long long)(b);                  \
        unit_checks++;                                                               \
        if (unit_a != unit_b) {                                                      \
            unit_failures++;                                                         \
            fprintf(stderr, "%s:%d: %s: %s == %lld, expected %s == %lld\n", __FILE__, __LINE__, __func__, #a, \
                    unit_a, #b, unit_b);                                             \
        }                                                                            \
    } while (0)

#define RUN(test)                                                                    \
    do {                                                                             \
        int unit_before = unit_failures;                                             \
        test();                                                                      \
        printf("%s %s\n", unit_failures == unit_before ? "ok  " : "FAIL", #test);    \
    } while (0)

#endif
