# CANopen node rules (included by firmware_sim/Makefile).
#   canopen-all    build/drive_sim (port + canopen + core + plant) and the unit tests
#   canopen-test   C unit tests of the CANopen services (against a drive test double)
#   canopen-cross  canopen/*.c + the generated table for Cortex-M4F, with sizes
#   canopen-bench  nothing in C: the CANopen benchmark is tests/bench/bench_canopen.py
#   canopen-fuzz   the CANopen fuzz target (fuzz/fuzz_co_node.c) lives in reliability.mk: rel-fuzz
#   canopen-doc    regenerate the object table in docs/object-dictionary.md
.PHONY: canopen-all canopen-test canopen-bench canopen-cross canopen-fuzz canopen-gen canopen-doc

CO_SRC    := $(wildcard canopen/co_*.c)
CO_HDR    := $(wildcard canopen/*.h) $(GEN)/od_table.h $(GEN)/od_params.h core/drv.h
CO_STAMP  := $(GEN)/.od_stamp
CO_CFLAGS := $(CSTD) $(WARN) $(OPT) -Icanopen -I$(GEN)
CO_BUILD  := $(BUILD)/co
PORT_SRC  := $(wildcard port/*.c)
PORT_HDR  := $(wildcard port/*.h)

# odgen writes od_params.h, od_table.[ch] and the EDS in one run (only files whose
# content changed are touched; the stamp records the run).
$(CO_STAMP): $(OD_YAML) tools/odgen.py
	@mkdir -p $(GEN)
	$(PYTHON) tools/odgen.py $(OD_YAML) $(GEN)
	@touch $@
$(GEN)/od_table.c $(GEN)/od_table.h $(GEN)/fftune_drive.eds: $(CO_STAMP)
	@test -f $@ || { rm -f $(CO_STAMP); $(MAKE) --no-print-directory $(CO_STAMP); }
canopen-gen: $(CO_STAMP)

# ---- unit tests: canopen services + drive test double; never linked into drive_sim.
# drv.h includes "drv_state.h" from its own directory, so the test build uses a copy of
# core/drv.h next to the double's drv_state.h (build/co_double/). ----
CO_TEST_SRC := $(wildcard canopen/tests/*.c)
CO_DOUBLE   := $(BUILD)/co_double
$(CO_DOUBLE)/drv.h: core/drv.h canopen/tests/drv_state.h
	@mkdir -p $(CO_DOUBLE)
	cp core/drv.h canopen/tests/drv_state.h $(CO_DOUBLE)/
$(BUILD)/co_test: $(CO_SRC) $(CO_TEST_SRC) $(wildcard canopen/tests/*.h) $(CO_HDR) $(GEN)/od_table.c $(CO_DOUBLE)/drv.h
	@mkdir -p $(BUILD)
	$(CC) $(CSTD) $(WARN) -O1 -g -DCO_SIM_BUILD -I$(CO_DOUBLE) -Icanopen -Icanopen/tests -I$(GEN) \
	    $(CO_SRC) $(CO_TEST_SRC) $(GEN)/od_table.c -lm -o $@

# ---- drive_sim: needs the core and the plant simulation (firmware core issue) ----
HAVE_CORE := $(and $(wildcard core/drv.c),$(wildcard core/drv_state.h),$(wildcard plant/sim.h))
ifneq ($(HAVE_CORE),)
$(BUILD)/drive_sim: $(CO_SRC) $(PORT_SRC) $(PORT_HDR) $(CO_HDR) $(GEN)/od_table.c $(LIBFWSIM)
	$(CC) $(CO_CFLAGS) -D_GNU_SOURCE -DCO_SIM_BUILD -Icore -Iplant -Iport \
	    $(CO_SRC) $(PORT_SRC) $(GEN)/od_table.c $(LIBFWSIM) -lm -o $@
canopen-all: $(CO_STAMP) $(BUILD)/drive_sim $(BUILD)/co_test
else
canopen-all: $(CO_STAMP) $(BUILD)/co_test
	@echo "canopen-all: build/drive_sim not built: core/drv.c, core/drv_state.h or plant/sim.h missing (firmware core not there yet)"
endif

canopen-test: canopen-all
	$(BUILD)/co_test

canopen-bench:
	@echo "canopen-bench: the CANopen benchmark runs from tests/bench/bench_canopen.py (make bench at the top level)"

# `make fuzz` runs rel-fuzz (reliability.mk), which fuzzes the node (fuzz_co_node) and the
# socketcand server (fuzz_scd); nothing CANopen-specific is left to do here.
canopen-fuzz:
	@true

canopen-doc: $(CO_STAMP)
	$(PYTHON) tools/odgen.py $(OD_YAML) $(GEN) --doc ../docs/object-dictionary.md

# ---- Cortex-M4F: the deployable CANopen part (no simulation objects) ----
CO_ARM_CC    ?= arm-none-eabi-gcc
CO_ARM_SIZE  ?= arm-none-eabi-size
CO_ARM_FLAGS := $(CSTD) $(WARN) -O2 -mcpu=cortex-m4 -mfpu=fpv4-sp-d16 -mfloat-abi=hard -mthumb \
                -ffreestanding -fno-math-errno -ffunction-sections -fdata-sections
CO_XOBJ      := $(BUILD)/cross/co
CO_XOBJS     := $(CO_SRC:canopen/%.c=$(CO_XOBJ)/%.o) $(CO_XOBJ)/od_table.o
$(CO_XOBJ)/%.o: canopen/%.c $(CO_HDR)
	@mkdir -p $(@D)
	$(CO_ARM_CC) $(CO_ARM_FLAGS) -Icanopen -Icore -I$(GEN) -c $< -o $@
$(CO_XOBJ)/od_table.o: $(GEN)/od_table.c $(CO_HDR)
	@mkdir -p $(@D)
	$(CO_ARM_CC) $(CO_ARM_FLAGS) -Icanopen -Icore -I$(GEN) -c $< -o $@
# Undefined symbols of the deployable objects may only be the drive API (drv_*), the
# generated table and mem* (which GCC requires of every freestanding environment): no OS
# or C-library call can slip in.
CO_ARM_NM    ?= arm-none-eabi-nm
ifneq ($(wildcard core/drv_state.h),)
canopen-cross: $(CO_STAMP) $(CO_XOBJS)
	@echo "== deployable CANopen objects (Cortex-M4F, -O2; text = flash, data+bss = RAM):"
	@$(CO_ARM_SIZE) -t $(CO_XOBJS)
	@bad=$$($(CO_ARM_NM) -u $(CO_XOBJS) | awk 'NF==2{print $$2}' | sort -u | grep -Ev '^(drv_[a-z0-9_]+|CO_OD|CO_OD_COUNT|co_[a-z0-9_]+|memcpy|memset|memcmp|memmove)$$' || true); \
	  if [ -n "$$bad" ]; then echo "canopen-cross: deployable CANopen code calls outside the drive API: $$bad" >&2; exit 1; fi; \
	  echo "undefined symbols: only drv_*, the generated table and mem* (link check passed)"
	@printf '#include "co_node.h"\nchar co_node_size_probe[sizeof(co_node_t)];\n' | \
	  $(CO_ARM_CC) $(CO_ARM_FLAGS) -Icanopen -Icore -I$(GEN) -x c -S -o - - | \
	  sed -n 's/^[[:space:]]*\.size[[:space:]]*co_node_size_probe, *\([0-9]*\)/sizeof(co_node_t) = \1 bytes of RAM (Cortex-M4F), allocated by the integrator/p'
else
canopen-cross:
	@echo "canopen-cross: core/drv_state.h missing (firmware core not there yet): nothing to compile"
endif
