/*
 * main.c - drive_sim: the simulated drive (plant + drive core, plant/sim.h) as a CANopen
 * slave (canopen/co_node.h) on a socketcand TCP server or a SocketCAN interface.
 *
 *   drive_sim [--can socketcand:HOST:PORT | --can socketcan:IFNAME] [--port N]
 *             [--node-id N] [--config FILE] [--axis ID:FILE ...] [--realtime] [--bitrate B] [--quiet]
 *
 * Several axes (--axis ID:FILE, repeated, up to DS_AXES_MAX): one process serves several
 * CANopen nodes, each with its own plant, drive core and recorder, on the one bus: every
 * frame of a node reaches the other nodes and the clients, and with --bitrate every node's
 * frames take their bit time on the one bus model (cbus source = the node's index). In
 * free-run each axis steps while its own run is active (its simulated time holds
 * otherwise); --realtime steps every axis each period (the axes must share fs_hz).
 *
 * Timing. CANopen timers (heartbeat, SDO timeout, PDO inhibit / event) always run on
 * CLOCK_MONOTONIC wall time.
 *  - default (free-run): while a run is settling or recording, the simulation steps as
 *    fast as the CPU allows (bus serviced about every millisecond); otherwise simulated
 *    time holds (no steps). So the data of a sequence of runs does not depend on the
 *    host's timing between them (reproducible, deterministic for a given seed), and an
 *    idle drive costs no CPU.
 *  - --realtime: one step per controller period against absolute CLOCK_MONOTONIC
 *    deadlines (clock_nanosleep TIMER_ABSTIME); a step that starts more than one period
 *    late counts as an overrun (printed at exit); more than 100 periods behind re-bases
 *    the schedule instead of catching up. Bus work is bounded per control period: after
 *    each step the bus is serviced in passes of bounded work (at most SCD_RT_READ bytes
 *    per client per pass) only while the next deadline is more than RT_MARGIN away, so
 *    a flood of frames slows the bus (TCP flow control holds the senders back), not the
 *    controller.
 * Bus model (--bitrate B, socketcand only): frames of the drive and of every client share
 * one simulated classic CAN bus at B bit/s (port/cbus.h: bit-exact frame length with
 * stuffing, arbitration by identifier); a frame reaches the others when its last bit has
 * been sent, time-stamped with that moment. Without --bitrate frames pass at once.
 * Readiness: one line on stdout, e.g.
 *   drive_sim: listening on socketcand 127.0.0.1:29536, node 1
 */
#include <errno.h>
#include <limits.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "cbus.h"
#include "co_node.h"
#include "fmu_plant.h"
#include "plant_config.h"
#include "scd.h"
#include "sim.h"
#include "sockcan.h"

#define DS_AXES_MAX CBUS_NODES

typedef struct {
    int node_id;
    const char *config;
} axis_opt_t;

typedef struct {
    bool socketcan;
    char host[64];
    int port;
    char ifname[32];
    int node_id;
    const char *config;
    bool realtime;
    bool quiet;
    bool check; /* --check: load and check the configuration(s), then exit */
    int bitrate; /* 0: no bus model */
    int n_axes;  /* --axis options given (0: one axis from --node-id / --config) */
    axis_opt_t axis[DS_AXES_MAX];
} opts_t;

#define SCD_RT_READ 256u              /* --realtime: bytes read per client per bus pass */
#define SCD_RT_WRITE 4096u            /* --realtime: bytes written per client per bus pass */
#define SCD_BUS_READ 1024u            /* --bitrate: at most ~100 frames per read */
#define CBUS_PAUSE_AT (CBUS_QUEUE / 2u) /* a client's bus queue this full: stop reading it */

struct app;

/* One axis: a CANopen node with its own plant, drive core and recorder. */
typedef struct {
    struct app *app;
    int index;             /* 0 .. n_axes - 1, its bus model source */
    int node_id;
    const char *config;
    plant_config_t cfg;
    sim_t sim;
    fmup_t *fmu;           /* the FMU plant (docs/fmu.md), NULL: the built-in plant */
    float *rec_buf;
    float *table_buf;
    co_node_t node;
    bool ready;            /* node initialised: frames are delivered to it */
    uint64_t steps;
} axis_t;

typedef struct app {
    opts_t o;
    int n_axes;
    axis_t ax[DS_AXES_MAX];
    scd_server_t *scd;
    cbus_t *bus;           /* NULL without --bitrate */
    int64_t realtime_offset_us; /* CLOCK_REALTIME - CLOCK_MONOTONIC (frame time stamps) */
    int can_fd;
    uint64_t now_us;
    uint64_t tx_time_ns;   /* bus time at which a node's next frame is queued */
    uint64_t steps;
    uint64_t overruns;
    uint64_t bus_passes;   /* bus service passes (poll + handle + flush) */
    uint64_t bus_late;     /* --realtime: periods whose bus work ran into the next deadline */
} app_t;

static volatile sig_atomic_t g_stop;

static void on_signal(int sig)
{
    (void)sig;
    g_stop = 1;
}

static uint64_t mono_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec;
}

static uint64_t mono_us(void)
{
    return mono_ns() / 1000u;
}

static int usage_error(const char *msg, const char *arg)
{
    fprintf(stderr, "drive_sim: error: %s%s%s\n", msg, arg ? ": " : "", arg ? arg : "");
    fprintf(stderr, "usage: drive_sim [--can socketcand:HOST:PORT | --can socketcan:IFNAME] [--port N] "
                    "[--node-id N] [--config FILE] [--axis ID:FILE ...] [--realtime] [--bitrate B] [--quiet] [--check]\n");
    return 2;
}

static bool parse_int(const char *s, long lo, long hi, int *out)
{
    char *end;
    errno = 0;
    long v = strtol(s, &end, 0);
    if (errno != 0 || end == s || *end != '\0' || v < lo || v > hi) {
        return false;
    }
    *out = (int)v;
    return true;
}

static int parse_can(opts_t *o, const char *spec)
{
    if (strncmp(spec, "socketcand:", 11) == 0) {
        const char *hp = spec + 11;
        const char *colon = strrchr(hp, ':');
        if (colon == NULL || colon == hp || (size_t)(colon - hp) >= sizeof o->host ||
            !parse_int(colon + 1, 0, 65535, &o->port)) {
            return usage_error("--can socketcand:HOST:PORT expected", spec);
        }
        memcpy(o->host, hp, (size_t)(colon - hp));
        o->host[colon - hp] = '\0';
        o->socketcan = false;
        return 0;
    }
    if (strncmp(spec, "socketcan:", 10) == 0) {
        const char *ifn = spec + 10;
        if (*ifn == '\0' || strlen(ifn) >= sizeof o->ifname) {
            return usage_error("--can socketcan:IFNAME expected", spec);
        }
        strcpy(o->ifname, ifn);
        o->socketcan = true;
        return 0;
    }
    return usage_error("unknown bus (socketcand:HOST:PORT or socketcan:IFNAME)", spec);
}

static int parse_args(opts_t *o, int argc, char **argv)
{
    memset(o, 0, sizeof *o);
    strcpy(o->host, "127.0.0.1");
    o->port = 29536;
    o->node_id = 1;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = (i + 1 < argc) ? argv[i + 1] : NULL;
        if (strcmp(a, "--can") == 0 && v) {
            if (parse_can(o, v) != 0) {
                return 2;
            }
            i++;
        } else if (strcmp(a, "--port") == 0 && v) {
            if (!parse_int(v, 0, 65535, &o->port)) {
                return usage_error("--port must be 0..65535", v);
            }
            i++;
        } else if (strcmp(a, "--node-id") == 0 && v) {
            if (!parse_int(v, 1, 127, &o->node_id)) {
                return usage_error("--node-id must be 1..127", v);
            }
            i++;
        } else if (strcmp(a, "--config") == 0 && v) {
            o->config = v;
            i++;
        } else if (strcmp(a, "--axis") == 0 && v) {
            const char *colon = strchr(v, ':');
            char idtext[8];
            int id;
            if (colon == NULL || colon == v || (size_t)(colon - v) >= sizeof idtext || colon[1] == '\0') {
                return usage_error("--axis ID:FILE expected", v);
            }
            memcpy(idtext, v, (size_t)(colon - v));
            idtext[colon - v] = '\0';
            if (!parse_int(idtext, 1, 127, &id)) {
                return usage_error("--axis: node id must be 1..127", v);
            }
            if (o->n_axes >= DS_AXES_MAX) {
                return usage_error("--axis: at most 8 axes", v);
            }
            for (int k = 0; k < o->n_axes; k++) {
                if (o->axis[k].node_id == id) {
                    return usage_error("--axis: duplicate node id", v);
                }
            }
            o->axis[o->n_axes].node_id = id;
            o->axis[o->n_axes].config = colon + 1;
            o->n_axes++;
            i++;
        } else if (strcmp(a, "--bitrate") == 0 && v) {
            if (!parse_int(v, CBUS_BITRATE_MIN, CBUS_BITRATE_MAX, &o->bitrate)) {
                return usage_error("--bitrate must be 10000..1000000 bit/s", v);
            }
            i++;
        } else if (strcmp(a, "--realtime") == 0) {
            o->realtime = true;
        } else if (strcmp(a, "--quiet") == 0) {
            o->quiet = true;
        } else if (strcmp(a, "--check") == 0) {
            o->check = true;
        } else if (strcmp(a, "--help") == 0 || strcmp(a, "-h") == 0) {
            printf("usage: drive_sim [--can socketcand:HOST:PORT | --can socketcan:IFNAME] [--port N] "
                   "[--node-id N] [--config FILE] [--axis ID:FILE ...] [--realtime] [--bitrate B] [--quiet] [--check]\n"
                   "  --can      bus (default socketcand:127.0.0.1:29536; --port 0 picks a free port)\n"
                   "  --node-id  CANopen node id 1..127 (default 1)\n"
                   "  --config   plant / controller configuration (configs/plant_*.yaml; default: built-in twomass)\n"
                   "  --axis     ID:FILE, repeated (up to 8): one node per axis on the one bus, node id\n"
                   "             and plant configuration each (instead of --node-id / --config)\n"
                   "  --realtime step at the controller rate on absolute deadlines (default: free-run)\n"
                   "  --bitrate  model a classic CAN bus of B bit/s shared by all nodes (socketcand only;\n"
                   "             default: frames pass at once)\n"
                   "  --check    load and check every configuration (and FMU), then exit: 0, or 2 with\n"
                   "             the error line; no bus is opened\n");
            exit(0);
        } else {
            return usage_error("unknown or incomplete option", a);
        }
    }
    if (o->bitrate != 0 && o->socketcan) {
        return usage_error("--bitrate models the socketcand bus; a SocketCAN interface has its own bit rate", NULL);
    }
    return 0;
}

/* ---- CANopen hooks ---- */

static void node_rx(app_t *app, const scd_frame_t *f, int except_axis);

static bool tx_hook(void *ctx, const co_frame_t *f)
{
    axis_t *ax = ctx;
    app_t *app = ax->app;
    scd_frame_t sf = {f->id, false, f->len, {0}};
    memcpy(sf.data, f->data, f->len);
    if (app->bus) {
        return cbus_submit(app->bus, ax->index, &sf, app->tx_time_ns); /* full queue: not sent (counted) */
    }
    /* the other nodes of this process see it at once (SocketCAN does not loop a socket's
     * own frames back to it) */
    node_rx(app, &sf, ax->index);
    if (app->o.socketcan) {
        return sockcan_write(app->can_fd, &sf);
    }
    scd_broadcast(app->scd, &sf, -1, 0u);
    return true;
}

static bool sim_hook(void *ctx, drv_param_id_t id, float *value)
{
    axis_t *ax = ctx;
    return sim_get_f32(&ax->sim, id, value) == DRV_OK;
}

static void reset_hook(void *ctx)
{
    /* NMT reset node: the drive and the plant start again from the configuration */
    axis_t *ax = ctx;
    char err[1024];
    if (ax->fmu != NULL && fmup_restart(ax->fmu, err, sizeof err) != 0) {
        fprintf(stderr, "drive_sim: reset node %d: %s\n", ax->node_id, err);
    }
    if (sim_init_ext(&ax->sim, &ax->cfg, ax->fmu ? fmup_ext(ax->fmu) : NULL, ax->rec_buf, ax->table_buf, err,
                     sizeof err) != 0) {
        fprintf(stderr, "drive_sim: reset node %d: %s\n", ax->node_id, err);
    }
}

/* A frame on the bus reaches every node of this process but its sender (except_axis, -1:
 * a frame from outside). */
static void node_rx(app_t *app, const scd_frame_t *f, int except_axis)
{
    if (f->ext) {
        return; /* CANopen uses 11-bit identifiers */
    }
    co_frame_t cf = {(uint16_t)f->id, f->len, {0}};
    memcpy(cf.data, f->data, f->len);
    for (int i = 0; i < app->n_axes; i++) {
        if (i != except_axis && app->ax[i].ready) {
            co_node_rx(&app->ax[i].node, &cf);
        }
    }
}

static bool any_run_active(const app_t *app)
{
    for (int i = 0; i < app->n_axes; i++) {
        if (co_node_run_active(&app->ax[i].node)) {
            return true;
        }
    }
    return false;
}

/* A frame from socketcand client `client` (or, with client -1, from SocketCAN). */
static void rx_hook(void *ctx, int client, const scd_frame_t *f)
{
    app_t *app = ctx;
    if (app->bus && client >= 0) {
        if (!cbus_submit(app->bus, CBUS_NODES + client, f, app->tx_time_ns)) {
            return; /* (not reached: reading pauses well before the queue is full) */
        }
        if (cbus_queued(app->bus, CBUS_NODES + client) >= CBUS_PAUSE_AT) {
            app->scd->client[client].rx_paused = true; /* TCP flow control holds it back */
        }
        return;
    }
    node_rx(app, f, -1);
    if (client >= 0) {
        scd_broadcast(app->scd, f, client, 0u); /* the other clients: one bus */
    }
}

/* The bus model delivers a frame whose last bit has been sent (at end_ns). */
static void deliver_hook(void *ctx, int src, const scd_frame_t *f, uint64_t end_ns)
{
    app_t *app = ctx;
    uint64_t saved = app->tx_time_ns;
    app->tx_time_ns = end_ns; /* the nodes answer as soon as the frame is in */
    node_rx(app, f, src < CBUS_NODES ? src : -1);
    uint64_t stamp_us = (uint64_t)((int64_t)(end_ns / 1000u) + app->realtime_offset_us);
    scd_broadcast(app->scd, f, src < CBUS_NODES ? -1 : src - CBUS_NODES, stamp_us);
    app->tx_time_ns = saved;
}

/* ---- bus service ---- */

/* One bus pass: wait up to timeout_ns for the bus (bounded by the bus model's and the
 * server's next event), handle what is ready, run the CANopen timers, write output.
 * Returns the number of ready descriptors. */
static int service_bus(app_t *app, uint64_t timeout_ns)
{
    struct pollfd pfd[1 + SCD_MAX_CLIENTS];
    int n;
    uint64_t now_ns = mono_ns();
    app->bus_passes++;
    if (app->o.socketcan) {
        pfd[0].fd = app->can_fd;
        pfd[0].events = POLLIN;
        pfd[0].revents = 0;
        n = 1;
    } else {
        if (app->bus) {
            for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
                scd_client_t *c = &app->scd->client[i];
                if (c->fd < 0 && cbus_queued(app->bus, CBUS_NODES + i) > 0u) {
                    cbus_flush_source(app->bus, CBUS_NODES + i); /* its client went away */
                }
                if (c->rx_paused && cbus_queued(app->bus, CBUS_NODES + i) < CBUS_PAUSE_AT / 2u) {
                    c->rx_paused = false;
                }
            }
            uint64_t ev = cbus_next_event_ns(app->bus);
            if (ev != UINT64_MAX) {
                timeout_ns = ev > now_ns ? (ev - now_ns < timeout_ns ? ev - now_ns : timeout_ns) : 0u;
            }
        }
        uint64_t wake_us = scd_next_wakeup_us(app->scd);
        if (wake_us != UINT64_MAX) {
            uint64_t now_us = now_ns / 1000u;
            uint64_t dt = wake_us > now_us ? (wake_us - now_us) * 1000u : 0u;
            timeout_ns = dt < timeout_ns ? dt : timeout_ns;
        }
        n = scd_pollfds(app->scd, pfd, now_ns / 1000u);
    }
    struct timespec ts = {(time_t)(timeout_ns / 1000000000u), (long)(timeout_ns % 1000000000u)};
    int r = ppoll(pfd, (nfds_t)n, &ts, NULL);
    now_ns = mono_ns();
    app->now_us = now_ns / 1000u;
    app->tx_time_ns = now_ns;
    if (r > 0) {
        if (app->o.socketcan) {
            scd_frame_t f;
            for (int k = 0; k < 256 && sockcan_read(app->can_fd, &f) == 1; k++) {
                rx_hook(app, -1, &f);
            }
        } else {
            scd_handle(app->scd, pfd, n, app->now_us, rx_hook, app);
        }
    }
    if (app->bus) {
        cbus_advance(app->bus, now_ns, deliver_hook, app);
    }
    for (int i = 0; i < app->n_axes; i++) {
        co_node_process(&app->ax[i].node, (uint32_t)app->now_us);
    }
    if (app->bus) {
        cbus_advance(app->bus, now_ns, deliver_hook, app); /* (the nodes' timers may have sent) */
    }
    if (!app->o.socketcan) {
        scd_expire(app->scd, app->now_us);
        scd_flush(app->scd, app->now_us);
    }
    return r;
}

static void loop_free_run(app_t *app)
{
    while (!g_stop) {
        if (any_run_active(app)) {
            /* as fast as the CPU allows (each axis while its own run is active); service
             * the bus every ~1 ms */
            uint64_t until = app->now_us + 1000u;
            do {
                for (int i = 0; i < app->n_axes; i++) {
                    axis_t *ax = &app->ax[i];
                    for (int k = 0; k < 64 && co_node_run_active(&ax->node); k++) {
                        sim_step(&ax->sim);
                        drv_background(sim_drv(&ax->sim)); /* statistics sums, between steps */
                        ax->steps++;
                        app->steps++;
                    }
                }
            } while (mono_us() < until && any_run_active(app));
            service_bus(app, 0u);
            continue;
        }
        /* idle: simulated time holds; wake for the bus or the 1 ms CANopen timer tick */
        service_bus(app, 1000000u);
    }
}

static void loop_realtime(app_t *app)
{
    const uint64_t period_ns = (uint64_t)(1e9 / app->ax[0].cfg.fs_hz + 0.5);
    struct timespec next;
    clock_gettime(CLOCK_MONOTONIC, &next);
    while (!g_stop) {
        uint64_t t = (uint64_t)next.tv_nsec + period_ns;
        next.tv_sec += (time_t)(t / 1000000000u);
        next.tv_nsec = (long)(t % 1000000000u);
        while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL) == EINTR && !g_stop) {
        }
        struct timespec now;
        clock_gettime(CLOCK_MONOTONIC, &now);
        int64_t late_ns = (int64_t)(now.tv_sec - next.tv_sec) * 1000000000 + (now.tv_nsec - next.tv_nsec);
        if (late_ns > (int64_t)period_ns) {
            app->overruns++;
            if (late_ns > 100 * (int64_t)period_ns) {
                next = now; /* far behind: re-base instead of catching up */
            }
        }
        for (int i = 0; i < app->n_axes; i++) {
            sim_step(&app->ax[i].sim);
            app->ax[i].steps++;
            app->steps++;
            drv_background(sim_drv(&app->ax[i].sim)); /* statistics sums, before the bus work */
        }
        /* bus work in bounded passes while the next deadline is far enough away (at least
         * one pass per period, so the bus is never starved) */
        uint64_t deadline_ns = (uint64_t)next.tv_sec * 1000000000u + (uint64_t)next.tv_nsec + period_ns;
        uint64_t margin_ns = period_ns / 4u;
        while (!g_stop) {
            int ready = service_bus(app, 0u);
            if (ready <= 0 || mono_ns() + margin_ns >= deadline_ns) {
                break;
            }
        }
        if (mono_ns() > deadline_ns) {
            app->bus_late++;
        }
    }
}

int main(int argc, char **argv)
{
    static app_t app;
    char err[2048];
    if (parse_args(&app.o, argc, argv) != 0) {
        return 2;
    }
    if (app.o.n_axes == 0) {
        app.o.axis[0].node_id = app.o.node_id;
        app.o.axis[0].config = app.o.config;
        app.o.n_axes = 1;
    }
    app.n_axes = app.o.n_axes;
    for (int i = 0; i < app.n_axes; i++) {
        axis_t *ax = &app.ax[i];
        ax->app = &app;
        ax->index = i;
        ax->node_id = app.o.axis[i].node_id;
        ax->config = app.o.axis[i].config;
        plant_config_defaults(&ax->cfg);
        if (ax->config && plant_config_load(ax->config, &ax->cfg, err, sizeof err) != 0) {
            fprintf(stderr, "drive_sim: error: %s\n", err);
            return 2;
        }
        ax->rec_buf = calloc(ax->cfg.rec_capacity ? ax->cfg.rec_capacity : 1u, sizeof(float));
        ax->table_buf = calloc(ax->cfg.table_capacity ? ax->cfg.table_capacity : 1u, sizeof(float));
        if (ax->rec_buf == NULL || ax->table_buf == NULL) {
            fprintf(stderr, "drive_sim: error: out of memory (recorder of %u floats)\n", (unsigned)ax->cfg.rec_capacity);
            return 2;
        }
        if (ax->cfg.fmu && (ax->fmu = fmup_open_file(ax->config, 1.0 / (double)(float)ax->cfg.fs_hz, err,
                                                     sizeof err)) == NULL) {
            fprintf(stderr, "drive_sim: error: %s\n", err); /* (the file and FMU named in err) */
            return 2;
        }
        if (sim_init_ext(&ax->sim, &ax->cfg, ax->fmu ? fmup_ext(ax->fmu) : NULL, ax->rec_buf, ax->table_buf, err,
                         sizeof err) != 0) {
            fprintf(stderr, "drive_sim: error: %s: %s\n", ax->config ? ax->config : "built-in config", err);
            return 2;
        }
        if (app.o.realtime && ax->cfg.fs_hz != app.ax[0].cfg.fs_hz) {
            fprintf(stderr, "drive_sim: error: --realtime steps every axis each period: node %d runs at %g Hz, "
                            "node %d at %g Hz (drive.fs_hz must be equal)\n",
                    ax->node_id, ax->cfg.fs_hz, app.ax[0].node_id, app.ax[0].cfg.fs_hz);
            return 2;
        }
    }
    if (app.o.check) {
        for (int i = 0; i < app.n_axes; i++) {
            fmup_close(app.ax[i].fmu);
        }
        return 0;
    }
    int bound = app.o.port;
    if (app.o.socketcan) {
        app.can_fd = sockcan_open(app.o.ifname, err, sizeof err);
        if (app.can_fd < 0) {
            fprintf(stderr, "drive_sim: error: %s\n", err);
            return 2;
        }
    } else {
        app.scd = calloc(1, sizeof *app.scd);
        if (app.scd == NULL || scd_open(app.scd, app.o.host, app.o.port, &bound, err, sizeof err) != 0) {
            fprintf(stderr, "drive_sim: error: %s\n", app.scd ? err : "out of memory");
            return 2;
        }
        if (app.o.realtime) {
            app.scd->read_budget = SCD_RT_READ;
            app.scd->write_budget = SCD_RT_WRITE;
        }
        if (app.o.bitrate != 0) {
            app.bus = calloc(1, sizeof *app.bus);
            if (app.bus == NULL || cbus_init(app.bus, (uint32_t)app.o.bitrate) != 0) {
                fprintf(stderr, "drive_sim: error: %s\n", app.bus ? "bad --bitrate" : "out of memory");
                return 2;
            }
            app.scd->read_budget = SCD_BUS_READ;
            struct timespec rt;
            clock_gettime(CLOCK_REALTIME, &rt);
            app.realtime_offset_us = ((int64_t)rt.tv_sec * 1000000 + rt.tv_nsec / 1000) - (int64_t)mono_us();
        }
    }
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);

    app.now_us = mono_us();
    app.tx_time_ns = app.now_us * 1000u;
    char nodes[DS_AXES_MAX * 4 + 8];
    size_t used = 0;
    for (int i = 0; i < app.n_axes; i++) {
        axis_t *ax = &app.ax[i];
        co_cfg_t cc;
        memset(&cc, 0, sizeof cc);
        cc.node_id = (uint8_t)ax->node_id;
        cc.tx = tx_hook;
        cc.tx_ctx = ax;
        cc.sim_get = sim_hook;
        cc.sim_ctx = ax;
        cc.reset_app = reset_hook;
        cc.app_ctx = ax;
        cc.table_capacity_bytes = ax->cfg.table_capacity * 4u;
        if (co_node_init(&ax->node, &cc, sim_drv(&ax->sim), (uint32_t)app.now_us) != 0) {
            fprintf(stderr, "drive_sim: error: node id %d: expected 1..127\n", ax->node_id);
            return 2;
        }
        ax->ready = true;
        used += (size_t)snprintf(nodes + used, sizeof nodes - used, "%s%d", i ? "," : "", ax->node_id);
    }
    const char *noun = app.n_axes > 1 ? "nodes" : "node";

    if (app.o.socketcan) {
        printf("drive_sim: listening on socketcan %s, %s %s\n", app.o.ifname, noun, nodes);
    } else {
        printf("drive_sim: listening on socketcand %s:%d, %s %s", app.o.host, bound, noun, nodes);
        if (app.bus) {
            printf(", CAN bus model %d bit/s", app.o.bitrate);
        }
        printf("\n");
    }
    fflush(stdout);

    if (app.o.realtime) {
        loop_realtime(&app);
    } else {
        loop_free_run(&app);
    }

    if (!app.o.quiet) {
        unsigned rx_frames = 0u, tx_frames = 0u, tx_dropped = 0u;
        for (int i = 0; i < app.n_axes; i++) {
            rx_frames += (unsigned)app.ax[i].node.rx_frames;
            tx_frames += (unsigned)app.ax[i].node.tx_frames;
            tx_dropped += (unsigned)app.ax[i].node.tx_dropped;
        }
        fprintf(stderr,
                "drive_sim: stopped: %llu steps, %llu overruns, %u frames received, %u sent, %u not sent, %llu bus passes, "
                "%llu periods with bus work past the next deadline",
                (unsigned long long)app.steps, (unsigned long long)app.overruns, rx_frames, tx_frames, tx_dropped, (unsigned long long)app.bus_passes,
                (unsigned long long)app.bus_late);
        if (app.scd) {
            fprintf(stderr, ", socketcand: %llu frames dropped at full client buffers, %llu bad commands, %llu refused connections"
                            ", %llu evicted in their handshake, %llu handshake timeouts",
                    (unsigned long long)app.scd->dropped, (unsigned long long)app.scd->garbage,
                    (unsigned long long)app.scd->refused, (unsigned long long)app.scd->evicted,
                    (unsigned long long)app.scd->handshake_timeouts);
        }
        if (app.bus) {
            fprintf(stderr, ", CAN bus model: %llu frames, %llu bits at %d bit/s, %llu dropped at full queues",
                    (unsigned long long)app.bus->frames, (unsigned long long)app.bus->bits, app.o.bitrate,
                    (unsigned long long)app.bus->dropped);
        }
        fprintf(stderr, "\n");
    }
    if (app.scd) {
        scd_close(app.scd);
    }
    for (int i = 0; i < app.n_axes; i++) {
        fmup_close(app.ax[i].fmu);
    }
    return 0;
}
