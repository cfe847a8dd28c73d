# CANopen node rules (included by firmware_sim/Makefile).
.PHONY: canopen-all canopen-test canopen-bench canopen-cross canopen-fuzz
canopen-all:
canopen-test:
canopen-bench:
canopen-cross:
canopen-fuzz:
