# Reliability rules (included by firmware_sim/Makefile, after canopen.mk).
#   rel-fuzz        build the libFuzzer targets (clang, ASan + UBSan) and run each for a
#                   bounded number of executions from its seed corpus; fails on any crash,
#                   leak or UB report, or if fewer than REL_FUZZ_MIN_EXECS ran in total.
#                   Figures: build/fuzz/summary.txt (executions, cov, ft, corpus per target).
#   rel-fuzz-replay run the committed regression inputs (fuzz/regress/) and the seeds once
#                   through the fuzz targets (seconds; part of rel-asan-test when clang is
#                   installed; without clang rel-asan-test still replays fuzz/regress/co_node
#                   through build/asan/replay_co_node, fuzz_co_node.c + fuzz/replay_main.c)
#   rel-asan-test   C unit tests (test_core, test_plant, co_test) and drive_sim built with
#                   -fsanitize=address,undefined -fno-sanitize-recover=all into build/asan/,
#                   the unit tests run under it; tests/test_reliability_*.py use
#                   build/asan/drive_sim when it exists.
.PHONY: rel-fuzz rel-fuzz-build rel-fuzz-seeds rel-fuzz-replay rel-asan-test rel-asan-build \
        $(FZ_TARGETS:%=rel-fuzz-run-%)

FZ_CC      ?= clang
comma      := ,
FZ_DIR     := $(BUILD)/fuzz
FZ_SAN     := -fsanitize=fuzzer,address,undefined -fno-sanitize-recover=all
FZ_CFLAGS  := $(CSTD) -Wall -Wextra -g -O2 -D_GNU_SOURCE -DCO_SIM_BUILD $(FZ_SAN) \
              -Icore -Iplant -Icanopen -Iport -I$(GEN)
# Parts that exist in this tree (each issue's code lands separately): targets whose
# sources are missing are left out with a message, never silently.
REL_HAVE_CO   := $(and $(wildcard canopen/co_node.c),$(wildcard core/drv.c),$(wildcard plant/sim.c))
REL_HAVE_PORT := $(and $(REL_HAVE_CO),$(wildcard port/scd.c))
FZ_TARGETS := $(strip $(if $(REL_HAVE_CO),fuzz_co_node) $(if $(REL_HAVE_PORT),fuzz_scd))
FZ_BINS    := $(FZ_TARGETS:%=$(FZ_DIR)/%)
REL_MISSING := $(if $(REL_HAVE_CO),,canopen/ core/ plant/ sources) $(if $(REL_HAVE_PORT),,port/scd.c)
# Executions per target (sum >= 10 million) and a wall-clock bound per target [s].
REL_FUZZ_RUNS      ?= fuzz_co_node=1500000 fuzz_scd=8600000
REL_FUZZ_MAX_TIME  ?= 3000
REL_FUZZ_MIN_EXECS ?= 10000000
REL_FUZZ_MAX_LEN   ?= fuzz_co_node=2048 fuzz_scd=600

# The simulated plant is the test fixture, not under test: sanitizers, but no coverage
# instrumentation (it would double the cost of an execution and steer nothing).
FZ_PLANT_OBJ := $(PLANT_SRC:plant/%.c=$(FZ_DIR)/plant/%.o)
# (every core header: sim_t holds drv_t, whose layout lstat.h / stat.h set)
$(FZ_DIR)/plant/%.o: plant/%.c $(wildcard plant/*.h) $(wildcard core/*.h) $(GEN)/od_params.h
	@mkdir -p $(@D)
	$(FZ_CC) $(subst fuzzer$(comma),,$(FZ_CFLAGS)) -c $< -o $@
$(FZ_DIR)/fuzz_co_node: fuzz/fuzz_co_node.c $(CORE_SRC) $(wildcard core/*.h) $(CO_SRC) $(CO_HDR) $(GEN)/od_table.c $(FZ_PLANT_OBJ)
	@mkdir -p $(@D)
	$(FZ_CC) $(FZ_CFLAGS) fuzz/fuzz_co_node.c $(CORE_SRC) $(CO_SRC) $(GEN)/od_table.c $(FZ_PLANT_OBJ) -lm -o $@
$(FZ_DIR)/fuzz_scd: fuzz/fuzz_scd.c port/scd.c port/scd.h
	@mkdir -p $(@D)
	$(FZ_CC) $(FZ_CFLAGS) fuzz/fuzz_scd.c port/scd.c -o $@

rel-fuzz-build: $(if $(REL_HAVE_CO),$(CO_STAMP)) $(FZ_BINS)
	@if [ -n "$(strip $(REL_MISSING))" ]; then echo "rel-fuzz: not built (missing: $(strip $(REL_MISSING)))"; fi

# Seeds: generated from the EDS and the protocol sequences of the conformance tests.
rel-fuzz-seeds: $(FZ_DIR)/seeds/.stamp
$(FZ_DIR)/seeds/.stamp: fuzz/gen_seeds.py $(GEN)/fftune_drive.eds
	$(PYTHON) fuzz/gen_seeds.py $(GEN)/fftune_drive.eds $(FZ_DIR)/seeds
	@touch $@

# Each target: its seeds + committed regression inputs, a fresh working corpus each time
# (so the figures are reproducible from the same starting point); libFuzzer's leak
# detection stays on; any crash / leak / UB stops make with the reproducer in build/fuzz/.
# One rule per target, so `make -j2 fuzz` runs them side by side.
rel-fuzz-run-%: rel-fuzz-build rel-fuzz-seeds
	@t=$*; runs=$$(echo "$(REL_FUZZ_RUNS)" | tr ' ' '\n' | sed -n "s/^$$t=//p"); \
	  maxlen=$$(echo "$(REL_FUZZ_MAX_LEN)" | tr ' ' '\n' | sed -n "s/^$$t=//p"); \
	  rm -rf $(FZ_DIR)/corpus/$$t $(FZ_DIR)/$$t.summary; mkdir -p $(FZ_DIR)/corpus/$$t $(FZ_DIR)/artifacts/$$t; \
	  cp $(FZ_DIR)/seeds/$${t#fuzz_}/* $(FZ_DIR)/corpus/$$t/; \
	  if ls fuzz/regress/$${t#fuzz_}/* >/dev/null 2>&1; then cp fuzz/regress/$${t#fuzz_}/* $(FZ_DIR)/corpus/$$t/; fi; \
	  echo "rel-fuzz: $$t: $$runs executions at most, $(REL_FUZZ_MAX_TIME) s at most"; \
	  $(FZ_DIR)/$$t -runs=$$runs -max_total_time=$(REL_FUZZ_MAX_TIME) -timeout=20 -seed=1 -max_len=$$maxlen \
	    -print_final_stats=1 -artifact_prefix=$(FZ_DIR)/artifacts/$$t/ \
	    $(FZ_DIR)/corpus/$$t > $(FZ_DIR)/$$t.log 2>&1 \
	    || { tail -40 $(FZ_DIR)/$$t.log >&2; echo "rel-fuzz: $$t FAILED (reproducer in $(FZ_DIR)/artifacts/$$t/, log $(FZ_DIR)/$$t.log)" >&2; exit 1; }; \
	  if grep -q "runtime error\|ERROR: AddressSanitizer\|ERROR: LeakSanitizer" $(FZ_DIR)/$$t.log; then \
	    tail -40 $(FZ_DIR)/$$t.log >&2; echo "rel-fuzz: $$t: sanitizer report" >&2; exit 1; fi; \
	  execs=$$(sed -n 's/^stat::number_of_executed_units: *//p' $(FZ_DIR)/$$t.log); \
	  last=$$(grep -E '^#[0-9]+' $(FZ_DIR)/$$t.log | tail -1); \
	  cov=$$(echo "$$last" | sed -n 's/.* cov: \([0-9]*\).*/\1/p'); \
	  ft=$$(echo "$$last" | sed -n 's/.* ft: \([0-9]*\).*/\1/p'); \
	  corp=$$(echo "$$last" | sed -n 's/.* corp: \([0-9]*\/[0-9]*[a-zA-Z]*\).*/\1/p'); \
	  secs=$$(sed -n 's/^Done [0-9]* runs in \([0-9]*\) second.*/\1/p' $(FZ_DIR)/$$t.log); \
	  echo "$$t executions=$$execs cov=$$cov ft=$$ft corpus=$$corp seconds=$$secs crashes=0" | tee $(FZ_DIR)/$$t.summary

rel-fuzz: $(if $(FZ_TARGETS),$(FZ_TARGETS:%=rel-fuzz-run-%),rel-fuzz-build)
	@if [ -z "$(FZ_TARGETS)" ]; then echo "rel-fuzz: no fuzz target can be built in this tree (missing: $(strip $(REL_MISSING)))"; exit 1; fi
	@cat $(FZ_TARGETS:%=$(FZ_DIR)/%.summary) > $(FZ_DIR)/summary.txt
	@total=$$(sed -n 's/.*executions=\([0-9]*\).*/\1/p' $(FZ_DIR)/summary.txt | awk '{s+=$$1} END {print s+0}'); \
	  echo "rel-fuzz: $$total executions in total, 0 crashes, 0 leaks, 0 UB reports" | tee -a $(FZ_DIR)/summary.txt; \
	  if [ $$total -lt $(REL_FUZZ_MIN_EXECS) ]; then echo "rel-fuzz: fewer than $(REL_FUZZ_MIN_EXECS) executions (the time bound cut a run short)" >&2; exit 1; fi

# Seeds and regression inputs once through each target (libFuzzer runs files given as
# arguments exactly once): a crash found earlier must stay fixed.
rel-fuzz-replay: rel-fuzz-build $(if $(FZ_TARGETS),rel-fuzz-seeds)
	@for t in $(FZ_TARGETS); do \
	  files="$$(ls $(FZ_DIR)/seeds/$${t#fuzz_}/*.bin) $$(ls fuzz/regress/$${t#fuzz_}/* 2>/dev/null)"; \
	  $(FZ_DIR)/$$t $$files > $(FZ_DIR)/$$t.replay.log 2>&1 \
	    || { tail -30 $(FZ_DIR)/$$t.replay.log >&2; echo "rel-fuzz-replay: $$t FAILED" >&2; exit 1; }; \
	  echo "rel-fuzz-replay: $$t: $$(echo $$files | wc -w) inputs (seeds + regressions) ran clean"; \
	done

# ---- ASan + UBSan build of the C unit tests and of drive_sim ----
ASAN_DIR    := $(BUILD)/asan
ASAN_CC     ?= $(CC)
ASAN_FLAGS  := -g -O1 -fno-omit-frame-pointer -fsanitize=address,undefined -fno-sanitize-recover=all
ASAN_ENV    := ASAN_OPTIONS=detect_leaks=1:abort_on_error=0:halt_on_error=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
ASAN_TESTS  := $(ASAN_DIR)/test_core $(ASAN_DIR)/test_plant $(if $(REL_HAVE_CO),$(ASAN_DIR)/co_test)
# fuzz_co_node without libFuzzer (fuzz/replay_main.c, any compiler): the regression inputs
# of fuzz/regress/co_node are replayed by every `make test`, with or without clang
ASAN_REPLAY := $(if $(REL_HAVE_CO),$(ASAN_DIR)/replay_co_node)
ASAN_BINS   := $(ASAN_TESTS) $(ASAN_REPLAY) $(if $(REL_HAVE_PORT),$(ASAN_DIR)/drive_sim)

$(ASAN_DIR)/test_core: tests/test_core.c tests/th.h $(GEN)/ms_vectors.h $(GEN)/od_params.h $(CORE_SRC) $(PLANT_SRC) $(wildcard core/*.h plant/*.h)
	@mkdir -p $(@D)
	$(ASAN_CC) $(CSTD) $(WARN) $(ASAN_FLAGS) -D_DEFAULT_SOURCE $(FW_INC) -Itests $< $(CORE_SRC) $(PLANT_SRC) -lm -o $@
$(ASAN_DIR)/test_plant: tests/test_plant.c tests/th.h $(GEN)/od_params.h $(CORE_SRC) $(PLANT_SRC) $(wildcard core/*.h plant/*.h)
	@mkdir -p $(@D)
	$(ASAN_CC) $(CSTD) $(WARN) $(ASAN_FLAGS) -D_DEFAULT_SOURCE $(FW_INC) -Itests $< $(CORE_SRC) $(PLANT_SRC) -lm -o $@
$(ASAN_DIR)/co_test: $(CO_SRC) $(CO_TEST_SRC) $(wildcard canopen/tests/*.h) $(CO_HDR) $(GEN)/od_table.c $(CO_DOUBLE)/drv.h
	@mkdir -p $(@D)
	$(ASAN_CC) $(CSTD) $(WARN) $(ASAN_FLAGS) -DCO_SIM_BUILD -I$(CO_DOUBLE) -Icanopen -Icanopen/tests -I$(GEN) \
	    $(CO_SRC) $(CO_TEST_SRC) $(GEN)/od_table.c -lm -o $@
$(ASAN_DIR)/replay_co_node: fuzz/replay_main.c fuzz/fuzz_co_node.c $(CORE_SRC) $(PLANT_SRC) $(CO_SRC) $(CO_HDR) $(GEN)/od_table.c $(wildcard core/*.h plant/*.h)
	@mkdir -p $(@D)
	$(ASAN_CC) $(CSTD) -Wall -Wextra $(ASAN_FLAGS) -D_GNU_SOURCE -DCO_SIM_BUILD -Icore -Iplant -Icanopen -Iport -I$(GEN) \
	    fuzz/replay_main.c fuzz/fuzz_co_node.c $(CORE_SRC) $(PLANT_SRC) $(CO_SRC) $(GEN)/od_table.c -lm -o $@
$(ASAN_DIR)/drive_sim: $(CO_SRC) $(PORT_SRC) $(PORT_HDR) $(CO_HDR) $(GEN)/od_table.c $(CORE_SRC) $(PLANT_SRC) $(wildcard core/*.h plant/*.h)
	@mkdir -p $(@D)
	$(ASAN_CC) $(CO_CFLAGS) $(ASAN_FLAGS) -D_GNU_SOURCE -DCO_SIM_BUILD -Icore -Iplant -Iport \
	    $(CO_SRC) $(PORT_SRC) $(GEN)/od_table.c $(CORE_SRC) $(PLANT_SRC) -lm -o $@

rel-asan-build: $(if $(REL_HAVE_CO),$(CO_STAMP)) $(ASAN_BINS)
	@if [ -n "$(strip $(REL_MISSING))" ]; then echo "rel-asan-build: CANopen parts not built (missing: $(strip $(REL_MISSING)))"; fi

rel-asan-test: rel-asan-build
	@set -e; for t in $(ASAN_TESTS); do echo "== $$t (ASan + UBSan)"; $(ASAN_ENV) $$t; done
	@if [ -n "$(ASAN_REPLAY)" ]; then files="$$(ls fuzz/regress/co_node/*)"; \
	  $(ASAN_ENV) $(ASAN_REPLAY) $$files > $(ASAN_DIR)/replay_co_node.log 2>&1 \
	    || { tail -30 $(ASAN_DIR)/replay_co_node.log >&2; echo "rel-asan-test: fuzz/regress/co_node replay FAILED" >&2; exit 1; }; \
	  echo "== fuzz/regress/co_node: $$(echo $$files | wc -w) regression inputs replayed clean ($(ASAN_REPLAY), no libFuzzer)"; fi
	@if [ -z "$(FZ_TARGETS)" ]; then echo "rel-asan-test: no fuzz targets in this tree: nothing to replay"; \
	elif command -v $(FZ_CC) >/dev/null 2>&1; then $(MAKE) --no-print-directory rel-fuzz-replay; \
	  else echo "rel-asan-test: $(FZ_CC) not installed: fuzz regression inputs not replayed (apt-get install clang)"; fi
