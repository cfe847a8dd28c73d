/*
 * replay_main.c - runs inputs once through a libFuzzer target without libFuzzer, so that
 * `make test` replays the committed regression inputs (fuzz/regress/) with gcc's ASan +
 * UBSan on a machine without clang (reliability.mk: build/asan/replay_co_node). A test
 * harness on the host (not deployable): it reads whole files into a heap buffer.
 *
 *   replay_co_node FILE...   exit 0 if every input ran; a property violation traps, a
 *                            sanitizer report aborts (non-zero exit either way)
 */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>

int LLVMFuzzerInitialize(int *argc, char ***argv);
int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

/* libFuzzer's own mutator, called by the target's custom mutator: never during a replay */
size_t LLVMFuzzerMutate(uint8_t *data, size_t size, size_t max_size);
size_t LLVMFuzzerMutate(uint8_t *data, size_t size, size_t max_size)
{
    (void)data;
    (void)max_size;
    return size;
}

#define REPLAY_MAX_BYTES (1u << 20)

int main(int argc, char **argv)
{
    if (argc < 2) {
        fprintf(stderr, "usage: %s FILE...\n", argv[0]);
        return 2;
    }
    (void)LLVMFuzzerInitialize(&argc, &argv);
    uint8_t *buf = malloc(REPLAY_MAX_BYTES);
    if (buf == NULL) {
        fprintf(stderr, "%s: out of memory\n", argv[0]);
        return 2;
    }
    for (int i = 1; i < argc; i++) {
        FILE *f = fopen(argv[i], "rb");
        if (f == NULL) {
            fprintf(stderr, "%s: cannot open %s\n", argv[0], argv[i]);
            free(buf);
            return 2;
        }
        size_t n = fread(buf, 1, REPLAY_MAX_BYTES, f);
        fclose(f);
        (void)LLVMFuzzerTestOneInput(buf, n);
        printf("replayed %s (%zu bytes)\n", argv[i], n);
    }
    free(buf);
    return 0;
}
