/*
 * th.h - a tiny unit-test harness (header only) for the firmware_sim C tests.
 *
 *   #include "th.h"
 *   static void test_something(void) { TH_ASSERT(1 + 1 == 2); TH_NEAR(x, 1.0, 1e-6); }
 *   int main(void) { TH_RUN(test_something); return th_finish(); }
 *
 * Each TH_RUN is one test; it passes when none of its assertions failed. Failed
 * assertions print "file:line: test: message" on stderr. th_finish() prints the closing
 * line "N passed, N failed" on stdout and returns the exit status (0 only if none failed).
 * Shared with the CANopen tests (firmware_sim/canopen/tests).
 */
#ifndef TH_H
#define TH_H

#include <math.h>
#include <stdio.h>

static int th_passed_count;
static int th_failed_count;
static int th_current_failures;
static const char *th_current_name = "";

static inline void th_fail(const char *file, int line, const char *msg)
{
    fprintf(stderr, "%s:%d: %s: %s\n", file, line, th_current_name, msg);
    th_current_failures++;
}

#define TH_ASSERT(cond)                                                            \
    do {                                                                           \
        if (!(cond)) {                                                             \
            th_fail(__FILE__, __LINE__, "assertion failed: " #cond);               \
        }                                                                          \
    } while (0)

/* |a - b| <= tol, printing both values when not */
#define TH_NEAR(a, b, tol)                                                         \
    do {                                                                           \
        double th_a_ = (double)(a), th_b_ = (double)(b), th_t_ = (double)(tol);    \
        if (!(fabs(th_a_ - th_b_) <= th_t_)) {                                     \
            char th_msg_[256];                                                     \
            snprintf(th_msg_, sizeof th_msg_, "%s = %.9g, %s = %.9g, tol %.3g",    \
                     #a, th_a_, #b, th_b_, th_t_);                                 \
            th_fail(__FILE__, __LINE__, th_msg_);                                  \
        }                                                                          \
    } while (0)

/* integer equality, printing both values when not */
#define TH_EQ(a, b)                                                                \
    do {                                                                           \
        long long th_a_ = (long long)(a), th_b_ = (long long)(b);                  \
        if (th_a_ != th_b_) {                                                      \
            char th_msg_[256];                                                     \
            snprintf(th_msg_, sizeof th_msg_, "%s = %lld, expected %s = %lld",     \
                     #a, th_a_, #b, th_b_);                                        \
            th_fail(__FILE__, __LINE__, th_msg_);                                  \
        }                                                                          \
    } while (0)

static inline void th_run_one(const char *name, void (*fn)(void))
{
    th_current_name = name;
    th_current_failures = 0;
    fn();
    if (th_current_failures == 0) {
        th_passed_count++;
    } else {
        th_failed_count++;
        fprintf(stderr, "FAILED: %s\n", name);
    }
}

#define TH_RUN(fn) th_run_one(#fn, fn)

static inline int th_finish(void)
{
    printf("%d passed, %d failed\n", th_passed_count, th_failed_count);
    return th_failed_count == 0 ? 0 : 1;
}

#endif /* TH_H */
