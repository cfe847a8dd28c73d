/* drv_double.h - helpers of the drive test double. */
#ifndef DRV_DOUBLE_H
#define DRV_DOUBLE_H
#include <stdint.h>
uint8_t rec_byte(uint32_t i);
#endif
