/*
 * cross_entry.c - link-check entry for `make cross`: references the whole drive API so
 * that the Cortex-M4F image links the deployable core with -nostdlib and only libm +
 * libgcc. Any OS or C-library call in core/ (malloc, printf, time, errno, ...) is then an
 * undefined symbol and the link fails. Statics stand for the port's fixed buffers.
 */
#include "drv.h"

static float cross_rec[4096];
static float cross_table[8192];
static float cross_stage[8192];
static drv_t cross_drv;
static uint8_t cross_bytes[64];

void cross_entry(void);

void cross_entry(void)
{
    drv_storage_t st = {cross_rec, 4096u, cross_table, 8192u, 2560.0f, cross_stage};
    drv_meas_t m = {0.0f, 0.0f};
    float f;
    uint32_t u;
    drv_monitor_t mon;
    (void)drv_init(&cross_drv, &st);
    drv_enable(&cross_drv, true);
    (void)drv_set_target(&cross_drv, 0.0f);
    (void)drv_set_f32(&cross_drv, DRV_P_KFC, 0.1f);
    (void)drv_get_f32(&cross_drv, DRV_P_KFC, &f);
    (void)drv_set_u32(&cross_drv, DRV_P_EXC_KIND, 3u);
    (void)drv_get_u32(&cross_drv, DRV_P_RUN_STATE, &u);
    (void)drv_table_write(&cross_drv, 0u, cross_bytes, 64u);
    (void)drv_table_commit(&cross_drv, 64u);
    (void)drv_table_read(&cross_drv, 0u, cross_bytes, 64u);
    (void)drv_table_size_bytes(&cross_drv);
    (void)drv_table_generation(&cross_drv);
    (void)drv_run_start(&cross_drv);
    (void)drv_step(&cross_drv, &m);
    (void)drv_rec_size_bytes(&cross_drv);
    (void)drv_rec_read(&cross_drv, 0u, cross_bytes, 4u);
    (void)drv_stat_size_bytes(&cross_drv);
    (void)drv_stat_read(&cross_drv, 0u, cross_bytes, 4u);
    drv_background(&cross_drv);
    (void)drv_background_catch_up(&cross_drv);
    (void)drv_lines_write(&cross_drv, 0u, cross_bytes, 4u);
    (void)drv_lines_commit(&cross_drv, 4u);
    (void)drv_lines_size_bytes(&cross_drv);
    (void)drv_lines_read(&cross_drv, 0u, cross_bytes, 4u);
    (void)drv_line_stats_size_bytes(&cross_drv);
    (void)drv_line_stats_read(&cross_drv, 0u, cross_bytes, 8u);
    (void)drv_set_u32(&cross_drv, DRV_P_TASK_MODE, 1u); /* the task (issue 26) */
    (void)drv_run_start(&cross_drv);
    (void)drv_step(&cross_drv, &m);
    (void)drv_task_stats_size_bytes(&cross_drv, DRV_TASK_DESIGN);
    (void)drv_task_stats_read(&cross_drv, DRV_TASK_LAST_DATA, 0u, cross_bytes, 8u);
    drv_get_monitor(&cross_drv, &mon);
    (void)drv_fault(&cross_drv);
    drv_run_abort(&cross_drv, DRV_STOP_ABORT_CMD);
    drv_safe_stop(&cross_drv, DRV_STOP_HEARTBEAT);
    for (;;) {
    }
}
