/*
 * sockcan.h - SocketCAN transport: a raw AF_CAN socket on a named interface (Linux only).
 */
#ifndef SOCKCAN_H
#define SOCKCAN_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "scd.h" /* scd_frame_t */

int sockcan_open(const char *ifname, char *err, size_t errlen); /* fd or -1 */
/* 1 frame read, 0 nothing (or a frame that is not classic CAN data), -1 error */
int sockcan_read(int fd, scd_frame_t *f);
/* true when the kernel took the frame; false when its queue is full */
bool sockcan_write(int fd, const scd_frame_t *f);

#endif
