/*
 * sockcan.c - SocketCAN raw socket (see sockcan.h).
 */
#include "sockcan.h"

#include <errno.h>
#include <linux/can.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <stdio.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

int sockcan_open(const char *ifname, char *err, size_t errlen)
{
    if (strlen(ifname) == 0 || strlen(ifname) >= IFNAMSIZ) {
        snprintf(err, errlen, "socketcan: bad interface name '%s'", ifname);
        return -1;
    }
    int fd = socket(PF_CAN, SOCK_RAW | SOCK_NONBLOCK | SOCK_CLOEXEC, CAN_RAW);
    if (fd < 0) {
        snprintf(err, errlen, "socketcan: socket(PF_CAN): %s (kernel without CAN support?)", strerror(errno));
        return -1;
    }
    /* a virtual bus (vcan) has no bit rate: a burst of frames (an SDO block of 127) arrives
     * at memory speed, so give the socket room (SO_RCVBUFFORCE needs CAP_NET_ADMIN) */
    int rcvbuf = 4 << 20;
    if (setsockopt(fd, SOL_SOCKET, SO_RCVBUFFORCE, &rcvbuf, sizeof rcvbuf) != 0) {
        (void)setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
    }
    unsigned idx = if_nametoindex(ifname);
    if (idx == 0) {
        snprintf(err, errlen, "socketcan: no interface '%s'", ifname);
        close(fd);
        return -1;
    }
    struct sockaddr_can a;
    memset(&a, 0, sizeof a);
    a.can_family = AF_CAN;
    a.can_ifindex = (int)idx;
    if (bind(fd, (struct sockaddr *)&a, sizeof a) != 0) {
        snprintf(err, errlen, "socketcan: bind %s: %s", ifname, strerror(errno));
        close(fd);
        return -1;
    }
    return fd;
}

int sockcan_read(int fd, scd_frame_t *f)
{
    struct can_frame cf;
    ssize_t r = read(fd, &cf, sizeof cf);
    if (r < 0) {
        return (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) ? 0 : -1;
    }
    if (r != (ssize_t)sizeof cf || (cf.can_id & (CAN_RTR_FLAG | CAN_ERR_FLAG)) || cf.can_dlc > 8) {
        return 0;
    }
    f->ext = (cf.can_id & CAN_EFF_FLAG) != 0;
    f->id = cf.can_id & (f->ext ? CAN_EFF_MASK : CAN_SFF_MASK);
    f->len = cf.can_dlc;
    memset(f->data, 0, sizeof f->data);
    memcpy(f->data, cf.data, cf.can_dlc);
    return 1;
}

bool sockcan_write(int fd, const scd_frame_t *f)
{
    struct can_frame cf;
    memset(&cf, 0, sizeof cf);
    cf.can_id = f->id | (f->ext ? CAN_EFF_FLAG : 0u);
    cf.can_dlc = f->len;
    memcpy(cf.data, f->data, f->len);
    return write(fd, &cf, sizeof cf) == (ssize_t)sizeof cf;
}
