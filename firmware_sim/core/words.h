/*
 * words.h - a byte range of a stream of little-endian 32-bit words (deployable, no state).
 *
 * The statistics objects (stat.c 0x2041, lstat.c 0x2043) compute each 32-bit word of their
 * data on demand instead of keeping a byte image; an SDO upload reads any byte range of it.
 */
#ifndef WORDS_H
#define WORDS_H

#include <stddef.h>
#include <stdint.h>

typedef uint32_t (*words_word_fn)(const void *ctx, uint32_t index);

/* Bytes [offset, offset + len) of the size-byte stream whose word i is word(ctx, i);
 * -1 (nothing written) for a range beyond the size or a NULL dst with len > 0. */
static inline int words_read(uint32_t size, words_word_fn word, const void *ctx, uint32_t offset,
                             uint8_t *dst, uint32_t len)
{
    if (offset > size || len > size - offset || (dst == NULL && len != 0u)) {
        return -1;
    }
    for (uint32_t b = 0u; b < len; b++) {
        uint32_t pos = offset + b;
        dst[b] = (uint8_t)(word(ctx, pos / 4u) >> (8u * (pos % 4u)));
    }
    return 0;
}

#endif /* WORDS_H */
