#!/bin/sh
# PID 1 of the SocketCAN test guest (busybox-static sh; installed as /init in the initramfs).
#
# Boot contract with tests/vm/guest.py (the host side):
#   - /modules.load lists the kernel modules to insmod, dependencies first (one path per line);
#   - virtio-9p tag "hostroot": the host's / (read-only); tag "job": the per-run job directory
#     (read-write) holding job.sh (the command) and timeout_s; this script writes stdout,
#     stderr, rc, timed_out (if the command hit its timeout) and init.log back into it;
#   - the host tree becomes writable in the guest through an overlay with a tmpfs upper layer,
#     so nothing ever reaches the host (qemu also exports it readonly=on).
# Any setup failure writes "rc" = 125 plus a line in init.log and powers off: the host side then
# reports init.log instead of waiting for its hard timeout.

PATH=/bin:/sbin
export PATH

/bin/busybox mkdir -p /proc /sys /dev /host /job /mnt/lower /mnt/rw /sbin /usr/bin /usr/sbin
/bin/busybox --install -s
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev

LOG=/init.log
log() { echo "vm-init: $*" >> "$LOG"; echo "vm-init: $*" > /dev/console; }
uptime_s() { cut -d' ' -f1 /proc/uptime; }

finish() {
    # $1: rc to record when no job ran (setup failure).
    if grep -q " /job " /proc/mounts; then
        [ -z "$1" ] || echo "$1" > /job/rc
        cat "$LOG" > /job/init.log
        sync
    fi
    poweroff -f
    echo o > /proc/sysrq-trigger
    sleep 5
}

fail() {
    log "FAILED: $*"
    finish 125
}

log "kernel $(uname -r) up at $(uptime_s) s"
while read -r mod; do
    [ -n "$mod" ] || continue
    insmod "$mod" >> "$LOG" 2>&1 || fail "insmod $mod"
done < /modules.load
log "modules loaded at $(uptime_s) s"

# msize: larger 9p messages cut the round trips per file read (python imports read many files).
mount -t 9p -o trans=virtio,version=9p2000.L,msize=262144,cache=loose,ro hostroot /mnt/lower \
    >> "$LOG" 2>&1 || fail "mount 9p hostroot"
mount -t 9p -o trans=virtio,version=9p2000.L,msize=262144 job /job >> "$LOG" 2>&1 \
    || fail "mount 9p job"

mount -t tmpfs -o mode=0755 tmpfs /mnt/rw || fail "mount tmpfs for overlay"
mkdir -p /mnt/rw/upper /mnt/rw/work
mount -t overlay -o lowerdir=/mnt/lower,upperdir=/mnt/rw/upper,workdir=/mnt/rw/work overlay /host \
    >> "$LOG" 2>&1 || fail "mount overlay over the host tree"

# Fresh kernel file systems and empty scratch directories inside the chroot.
mount -t proc proc /host/proc || fail "mount /host/proc"
mount -t sysfs sysfs /host/sys || fail "mount /host/sys"
mount -t devtmpfs devtmpfs /host/dev || fail "mount /host/dev"
mkdir -p /host/dev/pts /host/dev/shm
mount -t devpts devpts /host/dev/pts
# /tmp and /var/tmp stay as the overlay shows them (writable, guest-only): a repo checked
# out under /tmp (CI clones may live there) must stay visible in the chroot.
for d in /host/run /host/dev/shm; do
    mkdir -p "$d"
    mount -t tmpfs -o mode=1777 tmpfs "$d" || fail "mount tmpfs on $d"
done
mkdir -p /host/run/vmjob
mount --bind /job /host/run/vmjob || fail "bind the job directory into the chroot"

log "file systems mounted at $(uptime_s) s"
ip link set lo up || fail "ip link set lo up"
ip link add dev vcan0 type vcan >> "$LOG" 2>&1 || fail "ip link add dev vcan0 type vcan"
ip link set vcan0 up || fail "ip link set vcan0 up"

timeout_s=$(cat /job/timeout_s 2>/dev/null)
[ -n "$timeout_s" ] || fail "job directory has no timeout_s"
log "setup done at $(uptime_s) s; running the job (timeout ${timeout_s} s)"

# setsid: the job leads its own process group, so the watchdog kills it with all its children.
setsid chroot /host /bin/sh /run/vmjob/job.sh > /job/stdout 2> /job/stderr < /dev/null &
job_pid=$!
( sleep "$timeout_s"; echo "$timeout_s" > /job/timed_out; kill -KILL -- "-$job_pid" "$job_pid" ) \
    2>/dev/null &
watchdog_pid=$!
wait "$job_pid"
rc=$?
kill "$watchdog_pid" 2>/dev/null
echo "$rc" > /job/rc
log "job exited with $rc at $(uptime_s) s"
finish ""
