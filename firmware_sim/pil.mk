# Processor-in-the-loop rules (included by firmware_sim/Makefile): the drive on an
# STM32F405 (Cortex-M4F) under qemu-system-arm, tuned over an SLCAN link (port/mcu/).
#   pil          build/mcu/pil.elf (core + canopen + plant + port/mcu) for PIL_CONFIG, with
#                flash / RAM sizes; the plant is compiled in from PIL_CONFIG's sim: section
#   pil-bench    build/mcu/pil_bench.elf (instructions per drv_step, counted with -icount)
#   pil-test     the SLCAN parser's unit test on the host (build/mcu/test_slcan)
#   pil-run      starts the ELF in qemu on a free loopback port (port/mcu/pil_run.py)
.PHONY: pil pil-bench pil-test pil-run pil-check-tools

PIL_CONFIG ?= ../configs/pil.yaml
MCU        := $(BUILD)/mcu
MCU_DIR    := port/mcu
# Deployable flags as `make cross`; -ffp-contract=off is spelled out (it is the ISO C mode's
# default) because the determinism check compares the samples with drive_sim bit for bit.
MCU_CPU    := -mcpu=cortex-m4 -mfpu=fpv4-sp-d16 -mfloat-abi=hard -mthumb
# Port-level capacities (the 128 KiB RAM holds the PIL recorder and table; drive_sim is
# sized for the host and holds the drive's maxima):
#   LSTAT_LINES_MAX      the line statistics (core/lstat.h, 68 bytes per line) get 16 lines
#                        here (0x2040:9 tells the host; drive_sim holds 1024)
#   SIM_TABLE_STAGE_MAX  the table download staging buffer in sim_t (plant/sim.h) holds
#                        MCU_TABLE_MAX floats, not drive_sim's 8192 (32 KiB): the PIL
#                        configuration's drive.table_capacity must be at most this (cfggen
#                        refuses more; 0x2003:2 tells the host the table capacity)
# In MCU_BASE: every object that sees drv_t / sim_t (core, canopen, the plant's sim_t)
# must agree on their layout.
MCU_TABLE_MAX := 4096
MCU_BASE   := $(CSTD) $(WARN) -O2 -g $(MCU_CPU) -ffp-contract=off -ffunction-sections -fdata-sections \
              -DLSTAT_LINES_MAX=16u -DSIM_TABLE_STAGE_MAX=$(MCU_TABLE_MAX)u
MCU_DEPLOY := $(MCU_BASE) -Wdouble-promotion -ffreestanding -fsingle-precision-constant -fno-math-errno
# The plant simulation is double precision (software floating point on the M4F) and must
# not take -fsingle-precision-constant; its error messages go through mcu_snprintf.
MCU_PLANT  := $(MCU_BASE) -Dsnprintf=mcu_snprintf
MCU_INC    := -Icore -Iplant -Icanopen -I$(GEN) -I$(MCU_DIR) -I$(MCU)
MCU_LD     := $(MCU_CPU) -nostdlib -nostartfiles -T $(MCU_DIR)/stm32f405.ld -Wl,--gc-sections
# newlib's libm + the mem* / string functions; no syscalls are provided, so anything that
# needs an OS or the heap (malloc -> _sbrk, printf -> _write) fails the link.
MCU_LIBS   := -lm -lc -lgcc

MCU_CORE_OBJ  := $(CORE_SRC:core/%.c=$(MCU)/core/%.o)
MCU_CO_OBJ    := $(CO_SRC:canopen/%.c=$(MCU)/canopen/%.o) $(MCU)/canopen/od_table.o
MCU_PLANT_OBJ := $(MCU)/plant/plant.o $(MCU)/plant/sim.o $(MCU)/plant/pil_config.o
MCU_PORT_SRC  := startup.c uart.c slcan.c mcu_libc.c
MCU_PORT_OBJ  := $(MCU_PORT_SRC:%.c=$(MCU)/port/%.o)
MCU_HDRS      := $(wildcard core/*.h plant/*.h canopen/*.h $(MCU_DIR)/*.h) $(GEN)/od_params.h $(GEN)/od_table.h pil.mk

pil-check-tools:
	@command -v $(ARM_CC) >/dev/null 2>&1 || { echo "make pil: $(ARM_CC) not found (install: sudo make system-deps, packages gcc-arm-none-eabi libnewlib-arm-none-eabi)" >&2; exit 1; }

$(MCU)/core/%.o: core/%.c $(MCU_HDRS)
	@mkdir -p $(@D)
	$(ARM_CC) $(MCU_DEPLOY) $(MCU_INC) -c $< -o $@
$(MCU)/canopen/%.o: canopen/%.c $(MCU_HDRS)
	@mkdir -p $(@D)
	$(ARM_CC) $(MCU_DEPLOY) -DCO_SIM_BUILD $(MCU_INC) -c $< -o $@
$(MCU)/canopen/od_table.o: $(GEN)/od_table.c $(MCU_HDRS)
	@mkdir -p $(@D)
	$(ARM_CC) $(MCU_DEPLOY) -DCO_SIM_BUILD $(MCU_INC) -c $< -o $@
$(MCU)/plant/%.o: plant/%.c $(MCU_HDRS)
	@mkdir -p $(@D)
	$(ARM_CC) $(MCU_PLANT) $(MCU_INC) -c $< -o $@
$(MCU)/port/%.o: $(MCU_DIR)/%.c $(MCU_HDRS)
	@mkdir -p $(@D)
	$(ARM_CC) $(MCU_DEPLOY) $(MCU_INC) -c $< -o $@
$(MCU)/port/main.o: $(MCU_DIR)/main.c $(MCU_HDRS) $(MCU)/pil_config.h
	@mkdir -p $(@D)
	$(ARM_CC) $(MCU_DEPLOY) -DCO_SIM_BUILD $(MCU_INC) -c $< -o $@

# the plant configuration: PIL_CONFIG's sim.plant + sim.overrides -> plant.yaml (also what
# drive_sim reads in the determinism check) -> pil_config.[ch] (bit-exact doubles; the .c
# is compiled with the plant's flags, never with -fsingle-precision-constant)
$(MCU)/cfggen: $(MCU_DIR)/cfggen.c $(LIBFWSIM) pil.mk
	@mkdir -p $(@D)
	$(CC) $(CSTD) $(WARN) $(OPT) -D_DEFAULT_SOURCE -DCFGGEN_TABLE_MAX=$(MCU_TABLE_MAX)u $(FW_INC) $< $(LIBFWSIM) -lm -o $@
$(MCU)/plant.yaml: $(PIL_CONFIG) $(MCU_DIR)/pil_plant.py FORCE_PIL_CONFIG
	@mkdir -p $(@D)
	@$(PYTHON) $(MCU_DIR)/pil_plant.py $(PIL_CONFIG) $@.new > $(MCU)/node_id.new
	@if cmp -s $@.new $@ && cmp -s $(MCU)/node_id.new $(MCU)/node_id; then rm -f $@.new $(MCU)/node_id.new; \
	  else mv $@.new $@; mv $(MCU)/node_id.new $(MCU)/node_id; echo "pil: plant from $(PIL_CONFIG) -> $@"; fi
$(MCU)/pil_config.h: $(MCU)/plant.yaml $(MCU)/cfggen
	$(MCU)/cfggen $(MCU)/plant.yaml $$(cat $(MCU)/node_id) $(MCU)
$(MCU)/pil_config.c: $(MCU)/pil_config.h
$(MCU)/plant/pil_config.o: $(MCU)/pil_config.c $(MCU)/pil_config.h $(MCU_HDRS)
	@mkdir -p $(@D)
	$(ARM_CC) $(MCU_PLANT) $(MCU_INC) -c $< -o $@
.PHONY: FORCE_PIL_CONFIG
FORCE_PIL_CONFIG:

$(MCU)/pil.elf: $(MCU)/port/main.o $(MCU_PORT_OBJ) $(MCU_CORE_OBJ) $(MCU_CO_OBJ) $(MCU_PLANT_OBJ) $(MCU_DIR)/stm32f405.ld
	$(ARM_CC) $(MCU_LD) -Wl,-Map=$(MCU)/pil.map $(filter %.o,$^) $(MCU_LIBS) -o $@

pil: pil-check-tools gen $(CO_STAMP) $(MCU)/pil.elf
	@$(ARM_SIZE) $(MCU)/pil.elf
	@set -- $$($(ARM_SIZE) $(MCU)/pil.elf | awk 'NR==2{print $$1, $$2, $$3}'); \
	  stack=$$(( 0x$$($(ARM_NM) $(MCU)/pil.elf | awk '$$3=="_mcu_stack_size"{print $$1}') )); \
	  echo "pil: $(MCU)/pil.elf: flash $$(( $$1 + $$2 )) bytes (text $$1 + data $$2) of 1048576;" \
	       "RAM $$(( $$2 + $$3 )) bytes (data $$2 + bss $$3; recorder + table $$(( ($$(sed -n 's/#define PIL_REC_CAPACITY \([0-9]*\)u/\1/p' $(MCU)/pil_config.h) + $$(sed -n 's/#define PIL_TABLE_CAPACITY \([0-9]*\)u/\1/p' $(MCU)/pil_config.h)) * 4 )) bytes) + $$stack stack of 131072"

# ---- instructions per drv_step on the M4 (run by tests/bench/bench_mcu.py under qemu -icount) ----
$(MCU)/bench/bench.o: $(MCU_DIR)/bench.c $(MCU_HDRS) $(MCU)/pil_config.h
	@mkdir -p $(@D)
	$(ARM_CC) $(MCU_DEPLOY) $(MCU_INC) -c $< -o $@
$(MCU)/pil_bench.elf: $(MCU)/bench/bench.o $(MCU)/port/startup.o $(MCU)/port/uart.o $(MCU)/port/mcu_libc.o $(MCU_CORE_OBJ) $(MCU_PLANT_OBJ) $(MCU_DIR)/stm32f405.ld
	$(ARM_CC) $(MCU_LD) $(filter %.o,$^) $(MCU_LIBS) -o $@
pil-bench: pil-check-tools gen $(MCU)/pil_bench.elf

# ---- the SLCAN parser on the host (no hardware in it) ----
$(MCU)/test_slcan: $(MCU_DIR)/test_slcan.c $(MCU_DIR)/slcan.c $(MCU_DIR)/slcan.h tests/th.h
	@mkdir -p $(@D)
	$(CC) $(CSTD) $(WARN) -O1 -g -fsanitize=address,undefined -fno-sanitize-recover=all -I$(MCU_DIR) -Itests \
	    $(MCU_DIR)/test_slcan.c $(MCU_DIR)/slcan.c -o $@
pil-test: $(MCU)/test_slcan
	$(MCU)/test_slcan

pil-run: pil
	$(PYTHON) $(MCU_DIR)/pil_run.py --elf $(MCU)/pil.elf
