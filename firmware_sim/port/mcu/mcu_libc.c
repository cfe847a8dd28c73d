/*
 * mcu_libc.c - the one C-library function the plant simulation calls that the MCU build
 * must not take from newlib: snprintf (for error messages; newlib's formats %g through
 * its dtoa, which allocates from the heap). plant/ and sim.c are compiled for the MCU
 * with -Dsnprintf=mcu_snprintf. The configuration was checked on the host by cfggen, so
 * these messages are never produced on a good build; the format text is copied as is.
 */
#include <stdarg.h>
#include <stddef.h>
#include <string.h>

int mcu_snprintf(char *restrict buf, size_t n, const char *restrict fmt, ...);

int mcu_snprintf(char *restrict buf, size_t n, const char *restrict fmt, ...)
{
    size_t len = strlen(fmt);
    if (n > 0u) {
        size_t k = len < n - 1u ? len : n - 1u;
        memcpy(buf, fmt, k);
        buf[k] = '\0';
    }
    return (int)len;
}
