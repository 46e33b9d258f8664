/* A fake OpenHaptics HD library (libHD.so) over emulated Touch / Phantom devices: the
 * unmodified pyopenhaptics package loads it by its bare name and talks to it as to 3D Systems'.
 *
 * The devices: $HAPTICPROXY_EMU_HD_DEVICES = "NAME=BLOCK[,NAME=BLOCK...]" (the HD configuration
 * names, "Default Device" first; each BLOCK a shared block of hapticproxy.testing.emulators.block
 * with the physics of a simulated device behind it). Compiled by the test fixture (build.py)
 * with emu_block.h and emu_models.h generated from the Python declarations.
 *
 * The scheduler owns the clock, as OpenHaptics' does: hdStartScheduler starts a servo pthread
 * that ticks every 1 ms on absolute deadlines (clock_nanosleep TIMER_ABSTIME, then a short spin:
 * a device's servo clock is its hardware's, not a sleep's wake-up) and, each tick,
 * calls every scheduled callback (highest priority first); one returning HD_CALLBACK_DONE is
 * removed, hdScheduleSynchronous waits for its callback to be done. A callback frames its device
 * access with hdBeginFrame (the state is sampled: transform, velocities, buttons) and hdEndFrame
 * (the force set with hdSetDoublev(HD_CURRENT_FORCE) is committed to the device). Units as the HD
 * API's: positions in mm, velocities in mm/s, forces in N; the transform is a column-major 4x4.
 * The test hook emu_hd_set_lockstep(1) keeps the scheduler from starting its thread: the test
 * then calls emu_hd_tick() once per simulated period.
 *
 * Injected faults (the block's fault_* slots): unplugged -> hdEndFrame fails with HD_COMM_ERROR
 * and commits nothing; fault_error -> HD_DEVICE_FAULT; fault_late_ms -> each tick oversleeps by
 * that much (a servo thread that is not run in time); a different model is the block's model_id.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <pthread.h>
#include <signal.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <sched.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/prctl.h>
#include <time.h>
#include <unistd.h>

#include "emu_block.h"
#include "emu_models.h"

typedef unsigned int HHD;
typedef unsigned int HDenum;
typedef unsigned int HDCallbackCode;
typedef unsigned long HDSchedulerHandle;
typedef HDCallbackCode (*HDSchedulerCallback)(void *);
typedef struct { unsigned int errorCode; int internalErrorCode; HHD hHD; } HDErrorInfo;

#define HD_INVALID_HANDLE 0xFFFFFFFFu
#define HD_SUCCESS 0x000
#define HD_INVALID_ENUM 0x0100
#define HD_INVALID_OPERATION 0x0103
#define HD_BAD_HANDLE 0x0104
#define HD_DEVICE_FAULT 0x0300
#define HD_DEVICE_ALREADY_INITIATED 0x0301
#define HD_COMM_ERROR 0x0302
#define HD_COMM_CONFIG_ERROR 0x0303
#define HD_ILLEGAL_BEGIN 0x0400
#define HD_ILLEGAL_END 0x0401
#define HD_SCHEDULER_FULL 0x0501
#define HD_CALLBACK_DONE 0
#define HD_CALLBACK_CONTINUE 1
#define HD_CALIBRATION_OK 0x5000
#define HD_CALIBRATION_NEEDS_UPDATE 0x5001

#define MAXDEV 4
#define MAXCB 32
#define NSTATE (B_STATE_LAST - B_STATE_FIRST + 1)
#define S(slot) (d->frame[(slot) - B_STATE_FIRST])

struct dev {
    char name[128];
    volatile double *b;
    int open, force_on;
    double frame[NSTATE];
    double force[3];
    int in_frame;
};
struct cb { HDSchedulerCallback fn; void *data; unsigned prio; unsigned long id; int sync, done; };

static struct dev g_dev[MAXDEV];
static int g_ndev = -1, g_cur = -1;
static struct cb g_cb[MAXCB];
static int g_ncb = 0;
static unsigned long g_next_id = 1;
static pthread_mutex_t g_mx = PTHREAD_MUTEX_INITIALIZER;
static pthread_cond_t g_cv = PTHREAD_COND_INITIALIZER;
static pthread_t g_thread;
static int g_running = 0, g_lockstep = 0, g_stop = 0;
static HDErrorInfo g_err[16];
static int g_nerr = 0;
static pthread_mutex_t g_emx = PTHREAD_MUTEX_INITIALIZER;

static void push_error(unsigned code, HHD h) {
    pthread_mutex_lock(&g_emx);
    if (g_nerr < 16) { g_err[g_nerr].errorCode = code; g_err[g_nerr].internalErrorCode = 0; g_err[g_nerr].hHD = h; g_nerr++; }
    pthread_mutex_unlock(&g_emx);
}

static void attach(void) {
    if (g_ndev >= 0) return;
    g_ndev = 0;
    const char *env = getenv("HAPTICPROXY_EMU_HD_DEVICES");
    if (!env || !*env) return;
    char *list = strdup(env), *save = NULL;
    for (char *p = strtok_r(list, ",", &save); p && g_ndev < MAXDEV; p = strtok_r(NULL, ",", &save)) {
        char *eq = strchr(p, '=');
        if (!eq) continue;
        *eq = 0;
        int fd = open(eq + 1, O_RDWR);
        if (fd < 0) continue;
        void *m = mmap(NULL, 8 * B_NSLOTS, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
        close(fd);
        if (m == MAP_FAILED) continue;
        volatile double *b = (volatile double *)m;
        if ((long)b[B_MAGIC] != B_MAGIC_VALUE || (long)b[B_LAYOUT_VERSION] != B_LAYOUT_VERSION_VALUE) { munmap(m, 8 * B_NSLOTS); continue; }
        struct dev *d = &g_dev[g_ndev++];
        memset(d, 0, sizeof *d);
        snprintf(d->name, sizeof d->name, "%s", p);
        d->b = b;
        d->frame[B_QUAT - B_STATE_FIRST] = 1.0;
    }
    free(list);
}

static const struct emu_hd_model *model_of(struct dev *d) {
    int i = (int)d->b[B_MODEL_ID];
    return i >= 0 && i < EMU_HD_NMODELS ? &EMU_HD_MODELS[i] : NULL;
}

static struct dev *cur(void) {
    attach();
    if (g_cur < 0 || g_cur >= g_ndev || !g_dev[g_cur].open) { push_error(HD_INVALID_OPERATION, HD_INVALID_HANDLE); return NULL; }
    return &g_dev[g_cur];
}

/* ---------------------------------------------------------------------- devices */
HHD hdInitDevice(const char *name) {
    attach();
    const char *want = name && *name ? name : "Default Device";
    for (int i = 0; i < g_ndev; i++) {
        struct dev *d = &g_dev[i];
        if (strcmp(d->name, want) != 0) continue;
        if (d->b[B_FAULT_UNPLUGGED] != 0.0) break;
        double pid = (double)getpid();
        if (d->open || (d->b[B_OWNER_PID] != 0.0 && d->b[B_OWNER_PID] != pid && kill((pid_t)d->b[B_OWNER_PID], 0) == 0)) {
            push_error(HD_DEVICE_ALREADY_INITIATED, HD_INVALID_HANDLE);
            return HD_INVALID_HANDLE;
        }
        d->b[B_OWNER_PID] = pid;
        d->open = 1;
        g_cur = i;
        return (HHD)i;
    }
    push_error(HD_COMM_CONFIG_ERROR, HD_INVALID_HANDLE);
    return HD_INVALID_HANDLE;
}
void hdDisableDevice(HHD h) {
    attach();
    if (h >= (HHD)g_ndev || !g_dev[h].open) { push_error(HD_BAD_HANDLE, h); return; }
    struct dev *d = &g_dev[h];
    d->b[B_FORCE_ON] = 0.0;
    for (int k = 0; k < 6; k++) d->b[B_CMD + k] = 0.0;
    d->b[B_CMD_SEQ] += 1.0;
    d->b[B_OWNER_PID] = 0.0;
    d->open = 0;
    if (g_cur == (int)h) g_cur = -1;
}
HHD hdGetCurrentDevice(void) { return g_cur < 0 ? HD_INVALID_HANDLE : (HHD)g_cur; }
void hdMakeCurrentDevice(HHD h) {
    attach();
    if (h >= (HHD)g_ndev || !g_dev[h].open) { push_error(HD_BAD_HANDLE, h); return; }
    g_cur = (int)h;
}
HDErrorInfo hdGetError(void) {
    HDErrorInfo e = {HD_SUCCESS, 0, HD_INVALID_HANDLE};
    pthread_mutex_lock(&g_emx);
    if (g_nerr > 0) e = g_err[--g_nerr];
    pthread_mutex_unlock(&g_emx);
    return e;
}
const char *hdGetErrorString(unsigned code) {
    switch (code) {
    case HD_SUCCESS: return "no error";
    case HD_COMM_ERROR: return "communication error";
    case HD_COMM_CONFIG_ERROR: return "no device configured by that name";
    case HD_DEVICE_FAULT: return "device fault";
    case HD_DEVICE_ALREADY_INITIATED: return "device already initiated";
    case HD_BAD_HANDLE: return "bad handle";
    default: return "HD error";
    }
}
void hdEnable(HDenum cap) {
    struct dev *d = cur();
    if (d && cap == 0x4000) { d->force_on = 1; d->b[B_FORCE_ON] = 1.0; d->b[B_FORCE_OFF_CAUSE] = 0.0; }
}
void hdDisable(HDenum cap) {
    struct dev *d = cur();
    if (d && cap == 0x4000) { d->force_on = 0; d->b[B_FORCE_ON] = 0.0; d->b[B_FORCE_OFF_CAUSE] = 4.0; }
}
int hdIsEnabled(HDenum cap) {
    struct dev *d = cur();
    return d && cap == 0x4000 && d->b[B_FORCE_ON] != 0.0;
}
int hdCheckCalibration(void) {
    struct dev *d = cur();
    return d && d->b[B_CALIBRATED] != 0.0 ? HD_CALIBRATION_OK : HD_CALIBRATION_NEEDS_UPDATE;
}
void hdUpdateCalibration(int style) {
    struct dev *d = cur();
    if (d) d->b[B_CALIBRATED] = 1.0;  /* a Touch calibrates from its inkwell / encoders: no motion */
}

/* ---------------------------------------------------------------------- frames */
static void sample(struct dev *d) {
    volatile double *b = d->b;
    for (;;) {
        double q1 = b[B_STATE_SEQ];
        if (((long)q1) & 1) continue;
        atomic_thread_fence(memory_order_acquire);
        for (int i = B_STATE_FIRST; i <= B_STATE_LAST; i++) d->frame[i - B_STATE_FIRST] = b[i];
        atomic_thread_fence(memory_order_acquire);
        if (b[B_STATE_SEQ] == q1) return;
    }
}
void hdBeginFrame(HHD h) {
    attach();
    if (h >= (HHD)g_ndev || !g_dev[h].open) { push_error(HD_BAD_HANDLE, h); return; }
    struct dev *d = &g_dev[h];
    if (d->in_frame) { push_error(HD_ILLEGAL_BEGIN, h); return; }
    d->in_frame = 1;
    if (d->b[B_FAULT_UNPLUGGED] == 0.0) sample(d);  /* unplugged: the last sample stays */
    d->force[0] = d->force[1] = d->force[2] = 0.0;
}
void hdEndFrame(HHD h) {
    attach();
    if (h >= (HHD)g_ndev || !g_dev[h].open) { push_error(HD_BAD_HANDLE, h); return; }
    struct dev *d = &g_dev[h];
    if (!d->in_frame) { push_error(HD_ILLEGAL_END, h); return; }
    d->in_frame = 0;
    volatile double *b = d->b;
    if (b[B_FAULT_UNPLUGGED] != 0.0) { push_error(HD_COMM_ERROR, h); return; }
    if (b[B_FAULT_ERROR] != 0.0) {
        b[B_FORCE_ON] = 0.0;
        push_error(HD_DEVICE_FAULT, h);
        return;
    }
    for (int k = 0; k < 3; k++) b[B_CMD + k] = d->force[k];
    for (int k = 3; k < 6; k++) b[B_CMD + k] = 0.0;
    atomic_thread_fence(memory_order_release);
    b[B_CMD_SEQ] += 1.0;
}

/* ---------------------------------------------------------------------- state queries */
static void transform(struct dev *d, double *m) {
    double w = S(B_QUAT), x = S(B_QUAT + 1), y = S(B_QUAT + 2), z = S(B_QUAT + 3);
    double r[9] = {1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                   2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                   2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)};
    for (int c = 0; c < 3; c++)
        for (int rr = 0; rr < 3; rr++) m[4 * c + rr] = r[3 * rr + c];  /* column-major */
    m[3] = m[7] = m[11] = 0.0;
    m[12] = 1e3 * S(B_POS_M); m[13] = 1e3 * S(B_POS_M + 1); m[14] = 1e3 * S(B_POS_M + 2);
    m[15] = 1.0;
}
void hdGetDoublev(HDenum p, double *v) {
    struct dev *d = cur();
    if (!d || !v) return;
    const struct emu_hd_model *m = model_of(d);
    switch (p) {
    case 0x2050: for (int k = 0; k < 3; k++) v[k] = 1e3 * S(B_POS_M + k); break;          /* CURRENT_POSITION mm */
    case 0x2051: for (int k = 0; k < 3; k++) v[k] = 1e3 * S(B_VEL_M_S + k); break;        /* CURRENT_VELOCITY mm/s */
    case 0x2052: transform(d, v); break;                                                  /* CURRENT_TRANSFORM */
    case 0x2053: for (int k = 0; k < 3; k++) v[k] = S(B_ANGVEL_RAD_S + k); break;         /* ANGULAR_VELOCITY */
    case 0x2100: case 0x2150: v[0] = v[1] = v[2] = 0.0; break;                             /* joint / gimbal angles */
    case 0x2601: v[0] = d->b[B_PERIOD_S] > 0 ? 1.0 / d->b[B_PERIOD_S] : 0.0; break;       /* INSTANTANEOUS_UPDATE_RATE */
    case 0x2602: v[0] = m ? m->stiffness_n_per_m * 1e-3 : 0.0; break;                     /* NOMINAL_MAX_STIFFNESS N/mm */
    case 0x2609: v[0] = m ? m->damping_n_s_per_m * 1e-3 : 0.0; break;                     /* NOMINAL_MAX_DAMPING N s/mm */
    case 0x2603: v[0] = m ? m->max_force_n : 0.0; break;                                   /* NOMINAL_MAX_FORCE */
    case 0x2604: v[0] = m ? m->max_force_n : 0.0; break;  /* NOMINAL_MAX_CONTINUOUS_FORCE (the table has one force figure) */
    case 0x2551: case 0x2550: {                                                            /* workspace box mm */
        double r = m ? 1e3 * m->workspace_radius_m : 0.0;
        v[0] = v[1] = v[2] = -r; v[3] = v[4] = v[5] = r;
        break;
    }
    case 0x2700: for (int k = 0; k < 3; k++) v[k] = d->force[k]; break;                   /* CURRENT_FORCE */
    default: push_error(HD_INVALID_ENUM, (HHD)g_cur);
    }
}
void hdGetIntegerv(HDenum p, int *v) {
    struct dev *d = cur();
    if (!d || !v) return;
    const struct emu_hd_model *m = model_of(d);
    switch (p) {
    case 0x2000: v[0] = (int)S(B_BUTTONS); break;                                          /* CURRENT_BUTTONS */
    case 0x2600: v[0] = d->b[B_PERIOD_S] > 0 ? (int)lround(1.0 / d->b[B_PERIOD_S]) : 0; break;  /* UPDATE_RATE */
    case 0x2553: v[0] = 6; break;                                                          /* INPUT_DOF */
    case 0x2554: v[0] = 3; break;                                                          /* OUTPUT_DOF */
    case 0x2555: v[0] = 1 << 1; break;                                                     /* CALIBRATION_STYLE: auto */
    default: (void)m; push_error(HD_INVALID_ENUM, (HHD)g_cur);
    }
}
void hdGetLongv(HDenum p, long *v) { int i = 0; hdGetIntegerv(p, &i); if (v) v[0] = i; }
void hdGetBooleanv(HDenum p, unsigned char *v) { int i = 0; hdGetIntegerv(p, &i); if (v) v[0] = i != 0; }
void hdSetDoublev(HDenum p, const double *v) {
    struct dev *d = cur();
    if (!d || !v) return;
    if (p == 0x2700) { d->force[0] = v[0]; d->force[1] = v[1]; d->force[2] = v[2]; }   /* CURRENT_FORCE [N] */
    else push_error(HD_INVALID_ENUM, (HHD)g_cur);
}
void hdSetFloatv(HDenum p, const float *v) {
    if (!v) return;
    double dv[3] = {v[0], v[1], v[2]};
    hdSetDoublev(p, dv);
}
static char g_serial[32];
const char *hdGetString(HDenum p) {
    struct dev *d = cur();
    const struct emu_hd_model *m = d ? model_of(d) : NULL;
    switch (p) {
    case 0x2500: return "3.30.0 (emulated)";
    case 0x2501: return m ? m->name : "";
    case 0x2502: return "emulated";
    case 0x2503: return m ? m->vendor : "";
    case 0x2504: snprintf(g_serial, sizeof g_serial, "%d", d ? (int)d->b[B_SERIAL] : 0); return g_serial;
    case 0x2505: return "emulated";
    default: push_error(HD_INVALID_ENUM, (HHD)g_cur); return "";
    }
}

/* ---------------------------------------------------------------------- the scheduler */
static void tick(void) {
    /* one servo tick: every callback once, highest priority first (the array is kept sorted) */
    pthread_mutex_lock(&g_mx);
    for (int i = 0; i < g_ncb; i++) {
        struct cb c = g_cb[i];
        pthread_mutex_unlock(&g_mx);
        HDCallbackCode r = c.fn(c.data);
        pthread_mutex_lock(&g_mx);
        if (i < g_ncb && g_cb[i].id == c.id && r == HD_CALLBACK_DONE) {
            if (g_cb[i].sync) { g_cb[i].done = 1; pthread_cond_broadcast(&g_cv); }
            memmove(&g_cb[i], &g_cb[i + 1], (g_ncb - i - 1) * sizeof g_cb[0]);
            g_ncb--;
            i--;
        }
    }
    pthread_mutex_unlock(&g_mx);
    for (int i = 0; i < g_ndev; i++) if (g_dev[i].open) g_dev[i].b[B_SERVO_TICKS] += 1.0;
}

static void *servo(void *arg) {
    (void)arg;
    /* OpenHaptics runs its servo thread at a high priority: so does the fake, where it may
       (SCHED_FIFO needs the right to it; without, it runs as an ordinary thread) */
    struct sched_param sp;
    sp.sched_priority = 70;
    pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);
    struct timespec next;
    clock_gettime(CLOCK_MONOTONIC, &next);
    /* 1 kHz, as OpenHaptics' default; HAPTICPROXY_EMU_HD_RATE_HZ sets another (hdSetSchedulerRate's) */
    const char *rate_env = getenv("HAPTICPROXY_EMU_HD_RATE_HZ");
    double rate_hz = rate_env ? atof(rate_env) : 1000.0;
    const long period = rate_hz > 0.0 ? (long)(1e9 / rate_hz) : 1000000;
    /* HAPTICPROXY_EMU_HD_SPIN_US: the spin before each deadline (default 150 us, at most a
       quarter of the period: a FIFO thread spinning longer starves the process's other threads
       on a 2-core machine; 0: a plain sleep, the timer's own jitter) */
    const char *spin_env = getenv("HAPTICPROXY_EMU_HD_SPIN_US");
    long spin_ns = (long)((spin_env ? atof(spin_env) : 150.0) * 1000.0);
    if (spin_ns < 0) spin_ns = 0;
    if (spin_ns > period / 4) spin_ns = period / 4;
    prctl(PR_SET_TIMERSLACK, 1UL, 0UL, 0UL, 0UL);  /* the default 50 us slack would add to every sleep */
    while (!__atomic_load_n(&g_stop, __ATOMIC_ACQUIRE)) {
        struct timespec now;
        clock_gettime(CLOCK_MONOTONIC, &now);
        double late_us = ((now.tv_sec - next.tv_sec) * 1e9 + (now.tv_nsec - next.tv_nsec)) * 1e-3;
        for (int i = 0; i < g_ndev; i++) {
            if (!g_dev[i].open) continue;
            volatile double *b = g_dev[i].b;
            if (late_us > period * 1e-3) b[B_SERVO_LATE] += 1.0;
            if (late_us > b[B_SERVO_MAX_LATE_US]) b[B_SERVO_MAX_LATE_US] = late_us;
        }
        tick();
        double extra_ms = 0.0;
        for (int i = 0; i < g_ndev; i++) if (g_dev[i].open && g_dev[i].b[B_FAULT_LATE_MS] > extra_ms) extra_ms = g_dev[i].b[B_FAULT_LATE_MS];
        next.tv_nsec += period;
        while (next.tv_nsec >= 1000000000L) { next.tv_nsec -= 1000000000L; next.tv_sec++; }
        clock_gettime(CLOCK_MONOTONIC, &now);
        if ((now.tv_sec - next.tv_sec) * 1000000000L + (now.tv_nsec - next.tv_nsec) > 10 * period) next = now;  /* no burst */
        /* a device's servo clock is its hardware's (the Touch's 1 kHz frames), not a sleep's
           wake-up: sleep until spin_ns before the deadline, then spin to it (a plain sleep wakes
           25-75 us late on a VM, and that, not the tick, would be the jitter measured) */
        struct timespec wake = next;
        wake.tv_nsec -= spin_ns;
        while (wake.tv_nsec < 0) { wake.tv_nsec += 1000000000L; wake.tv_sec--; }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &wake, NULL);
        do { clock_gettime(CLOCK_MONOTONIC, &now); }
        while (now.tv_sec < next.tv_sec || (now.tv_sec == next.tv_sec && now.tv_nsec < next.tv_nsec));
        if (extra_ms > 0.0) {
            struct timespec ex = {(time_t)(extra_ms / 1000.0), (long)(fmod(extra_ms, 1000.0) * 1e6)};
            nanosleep(&ex, NULL);
        }
    }
    return NULL;
}

void hdStartScheduler(void) {
    attach();
    if (g_running) return;
    g_running = 1;
    if (g_lockstep) return;
    __atomic_store_n(&g_stop, 0, __ATOMIC_RELEASE);
    if (pthread_create(&g_thread, NULL, servo, NULL) != 0) { g_running = 0; push_error(HD_SCHEDULER_FULL, HD_INVALID_HANDLE); }
}
void hdStopScheduler(void) {
    if (!g_running) return;
    g_running = 0;
    if (g_lockstep) return;
    __atomic_store_n(&g_stop, 1, __ATOMIC_RELEASE);
    pthread_join(g_thread, NULL);
}
static unsigned long schedule(HDSchedulerCallback fn, void *data, unsigned prio, int sync) {
    pthread_mutex_lock(&g_mx);
    if (g_ncb >= MAXCB) { pthread_mutex_unlock(&g_mx); push_error(HD_SCHEDULER_FULL, HD_INVALID_HANDLE); return 0; }
    int at = g_ncb;
    while (at > 0 && g_cb[at - 1].prio < prio) at--;
    memmove(&g_cb[at + 1], &g_cb[at], (g_ncb - at) * sizeof g_cb[0]);
    unsigned long id = g_next_id++;
    g_cb[at] = (struct cb){fn, data, prio, id, sync, 0};
    g_ncb++;
    pthread_mutex_unlock(&g_mx);
    return id;
}
HDSchedulerHandle hdScheduleAsynchronous(HDSchedulerCallback fn, void *data, unsigned short prio) {
    return schedule(fn, data, prio, 0);
}
void hdScheduleSynchronous(HDSchedulerCallback fn, void *data, unsigned short prio) {
    if (!g_running || g_lockstep) {  /* no servo thread to wait for: run it here until done */
        for (int i = 0; i < 100000 && fn(data) != HD_CALLBACK_DONE; i++) {}
        return;
    }
    unsigned long id = schedule(fn, data, prio, 1);
    pthread_mutex_lock(&g_mx);
    for (;;) {
        int found = 0;
        for (int i = 0; i < g_ncb; i++) if (g_cb[i].id == id) found = 1;
        if (!found) break;
        pthread_cond_wait(&g_cv, &g_mx);
    }
    pthread_mutex_unlock(&g_mx);
}
void hdUnschedule(HDSchedulerHandle h) {
    pthread_mutex_lock(&g_mx);
    for (int i = 0; i < g_ncb; i++)
        if (g_cb[i].id == h) { memmove(&g_cb[i], &g_cb[i + 1], (g_ncb - i - 1) * sizeof g_cb[0]); g_ncb--; break; }
    pthread_cond_broadcast(&g_cv);
    pthread_mutex_unlock(&g_mx);
}
int hdWaitForCompletion(HDSchedulerHandle h, unsigned param) { (void)param; (void)h; return 1; }
double hdGetSchedulerTimeStamp(void) { return 1e-3; }

/* ---------------------------------------------------------------------- test hooks (not HD API) */
void emu_hd_set_lockstep(int on) { g_lockstep = on; }
void emu_hd_tick(void) { tick(); }
void emu_hd_reattach(void) {
    hdStopScheduler();
    pthread_mutex_lock(&g_mx);
    g_ncb = 0;
    pthread_mutex_unlock(&g_mx);
    for (int i = 0; i < g_ndev; i++) {
        if (g_dev[i].open) g_dev[i].b[B_OWNER_PID] = 0.0;
        munmap((void *)g_dev[i].b, 8 * B_NSLOTS);
    }
    g_ndev = -1;
    g_cur = -1;
    g_nerr = 0;
    attach();
}
