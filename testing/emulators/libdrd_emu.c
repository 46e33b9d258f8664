/* A fake Force Dimension SDK (libdrd.so, which also holds the dhd* functions) over emulated
 * devices: the unmodified forcedimension-core package loads it through $FDSDK and talks to it
 * exactly as to the vendor's library.
 *
 * The devices: one shared block per device (hapticproxy.testing.emulators.block), listed in
 * $HAPTICPROXY_EMU_BLOCKS (paths separated by ':'), each with the physics of a simulated device
 * behind it (physics.py, in this process or its own). This file is compiled by the test fixture
 * (build.py) with emu_block.h (the block layout) and emu_models.h (the models' names and
 * figures) generated from the Python declarations, and with emu_stubs.c: every other symbol the
 * installed package binds at import, each failing with DHD_ERROR_NOT_IMPLEMENTED.
 *
 * Real behaviour: SDK version; device count, open (first free / by index / serial / type) and
 * close, one process per device (DHD_ERROR_DEVICE_IN_USE otherwise); system type and name,
 * serial, what the model has (wrist, gripper, active parts), its maximum force, the
 * communication rate; position, orientation (frame and angles), velocities, gripper angle,
 * buttons; force / torque / gripper force commands (DHD_MOTOR_SATURATED above the maximum);
 * enable force; status (force on, the cause of the last cut, error); the firmware watchdog
 * (expert mode, as the SDK requires); drdAutoInit / drdIsInitialized calibration; errors:
 * -1 and dhdErrorGetLast(). Injected faults (the block's fault_* slots): an unplugged device
 * fails every call with DHD_ERROR_COM; fault_error makes every call fail with that code.
 */
#define _GNU_SOURCE
#include <fcntl.h>
#include <math.h>
#include <signal.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <time.h>
#include <unistd.h>

#include "emu_block.h"
#include "emu_models.h"

#define MAXDEV 8
#define DHD_NO_ERROR 0
#define DHD_ERROR 1
#define DHD_ERROR_COM 2
#define DHD_ERROR_NO_DEVICE_FOUND 5
#define DHD_ERROR_NOT_AVAILABLE 6
#define DHD_ERROR_EXPERT_MODE_DISABLED 9
#define DHD_ERROR_NOT_IMPLEMENTED 10
#define DHD_ERROR_DEVICE_NOT_READY 12
#define DHD_ERROR_INVALID_INDEX 15
#define DHD_ERROR_NULL_ARGUMENT 17
#define DHD_ERROR_NOT_ENABLED 19
#define DHD_ERROR_DEVICE_IN_USE 20
#define DHD_ERROR_INVALID 21
#define DHD_MOTOR_SATURATED 2
#define DHD_MAX_STATUS 17

static volatile double *g_blk[MAXDEV];
static int g_ndev = -1;
static int g_open[MAXDEV];
static int g_cur = -1;
static int g_expert = 0;
static __thread int g_err = 0;

static const char *err_str(int e) {
    switch (e) {
    case DHD_NO_ERROR: return "no error";
    case DHD_ERROR_COM: return "communication error between the host and the haptic device";
    case DHD_ERROR_NO_DEVICE_FOUND: return "no haptic device found";
    case DHD_ERROR_NOT_AVAILABLE: return "feature not available";
    case DHD_ERROR_EXPERT_MODE_DISABLED: return "expert mode is disabled";
    case DHD_ERROR_NOT_IMPLEMENTED: return "feature not implemented (emulator)";
    case DHD_ERROR_DEVICE_NOT_READY: return "device not ready";
    case DHD_ERROR_INVALID_INDEX: return "invalid index";
    case DHD_ERROR_NULL_ARGUMENT: return "null argument";
    case DHD_ERROR_NOT_ENABLED: return "feature not enabled";
    case DHD_ERROR_DEVICE_IN_USE: return "device already in use";
    default: return "undocumented error";
    }
}

static int fail(int e) { g_err = e; return -1; }

static void attach(void) {
    if (g_ndev >= 0) return;
    g_ndev = 0;
    const char *env = getenv("HAPTICPROXY_EMU_BLOCKS");
    if (!env || !*env) return;
    char *list = strdup(env), *save = NULL;
    for (char *p = strtok_r(list, ":", &save); p && g_ndev < MAXDEV; p = strtok_r(NULL, ":", &save)) {
        int fd = open(p, O_RDWR);
        if (fd < 0) continue;
        void *m = mmap(NULL, 8 * B_NSLOTS, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
        close(fd);
        if (m == MAP_FAILED) continue;
        volatile double *b = (volatile double *)m;
        if ((long)b[B_MAGIC] != B_MAGIC_VALUE || (long)b[B_LAYOUT_VERSION] != B_LAYOUT_VERSION_VALUE) {
            munmap(m, 8 * B_NSLOTS);
            continue;
        }
        g_blk[g_ndev++] = b;
    }
    free(list);
}

/* The device an SDK call addresses (ID -1: the current one), or NULL with the error set; a
 * device that is unplugged or in an injected error state fails here, as the SDK's USB layer does. */
static volatile double *dev(char id) {
    attach();
    int i = id < 0 ? g_cur : id;
    if (i < 0 || i >= g_ndev || !g_open[i]) { fail(DHD_ERROR_INVALID_INDEX); return NULL; }
    volatile double *b = g_blk[i];
    if (b[B_FAULT_UNPLUGGED] != 0.0) { fail(DHD_ERROR_COM); return NULL; }
    if (b[B_FAULT_ERROR] != 0.0) { fail((int)b[B_FAULT_ERROR]); return NULL; }
    return b;
}

static const struct emu_fd_model *model_of(volatile double *b) { return emu_fd_model((int)b[B_MODEL_ID]); }

/* one consistent sample of the state under the block's sequence lock */
static void sample(volatile double *b, double *s) {
    for (;;) {
        double q1 = b[B_STATE_SEQ];
        if (((long)q1) & 1) continue;
        atomic_thread_fence(memory_order_acquire);
        for (int i = B_STATE_FIRST; i <= B_STATE_LAST; i++) s[i - B_STATE_FIRST] = b[i];
        atomic_thread_fence(memory_order_acquire);
        if (b[B_STATE_SEQ] == q1) return;
    }
}
#define S(slot) (s[(slot) - B_STATE_FIRST])

/* ---------------------------------------------------------------------- version, errors */
void dhdGetSDKVersion(int *major, int *minor, int *release, int *revision) {
    if (major) *major = 3;
    if (minor) *minor = 17;
    if (release) *release = 6;
    if (revision) *revision = 0;
}
int dhdErrorGetLast(void) { return g_err; }
const char *dhdErrorGetLastStr(void) { return err_str(g_err); }
const char *dhdErrorGetStr(int e) { return err_str(e); }
double dhdGetTime(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}
int dhdEnableExpertMode(void) { g_expert = 1; return 0; }
int dhdDisableExpertMode(void) { g_expert = 0; return 0; }

/* ---------------------------------------------------------------------- devices */
int dhdGetDeviceCount(void) {
    attach();
    int n = 0;
    for (int i = 0; i < g_ndev; i++) n += g_blk[i][B_FAULT_UNPLUGGED] == 0.0;
    return n;
}
int dhdGetAvailableCount(void) {
    attach();
    int n = 0;
    for (int i = 0; i < g_ndev; i++) n += g_blk[i][B_FAULT_UNPLUGGED] == 0.0 && g_blk[i][B_OWNER_PID] == 0.0;
    return n;
}

static int open_index(int i) {
    attach();
    if (i < 0 || i >= g_ndev) return fail(DHD_ERROR_NO_DEVICE_FOUND);
    volatile double *b = g_blk[i];
    if (b[B_FAULT_UNPLUGGED] != 0.0) return fail(DHD_ERROR_NO_DEVICE_FOUND);
    double pid = (double)getpid();
    if (b[B_OWNER_PID] != 0.0 && b[B_OWNER_PID] != pid && kill((pid_t)b[B_OWNER_PID], 0) == 0)
        return fail(DHD_ERROR_DEVICE_IN_USE);
    b[B_OWNER_PID] = pid;
    g_open[i] = 1;
    g_cur = i;
    g_err = 0;
    return i;
}
int dhdOpenID(char id) { return open_index(id); }
int dhdOpen(void) {
    attach();
    int busy = 0;
    for (int i = 0; i < g_ndev; i++) {
        if (g_open[i] || g_blk[i][B_FAULT_UNPLUGGED] != 0.0) continue;
        int r = open_index(i);
        if (r >= 0) return r;
        busy |= g_err == DHD_ERROR_DEVICE_IN_USE;
    }
    return fail(busy ? DHD_ERROR_DEVICE_IN_USE : DHD_ERROR_NO_DEVICE_FOUND);
}
int dhdOpenSerial(int serial) {
    attach();
    for (int i = 0; i < g_ndev; i++)
        if ((int)g_blk[i][B_SERIAL] == serial) return open_index(i);
    return fail(DHD_ERROR_NO_DEVICE_FOUND);
}
int dhdOpenType(int type) {
    attach();
    for (int i = 0; i < g_ndev; i++)
        if ((int)g_blk[i][B_MODEL_ID] == type && !g_open[i]) return open_index(i);
    return fail(DHD_ERROR_NO_DEVICE_FOUND);
}
int dhdClose(char id) {
    attach();
    int i = id < 0 ? g_cur : id;
    if (i < 0 || i >= g_ndev || !g_open[i]) return fail(DHD_ERROR_INVALID_INDEX);
    volatile double *b = g_blk[i];
    b[B_FORCE_ON] = 0.0;  /* the SDK disables forces on close */
    for (int k = 0; k < 7; k++) b[B_CMD + k] = 0.0;
    b[B_CMD_SEQ] += 1.0;
    b[B_OWNER_PID] = 0.0;
    g_open[i] = 0;
    if (g_cur == i) g_cur = -1;
    return 0;
}
int dhdSetDevice(char id) {
    attach();
    if (id < 0 || id >= g_ndev || !g_open[(int)id]) return fail(DHD_ERROR_INVALID_INDEX);
    g_cur = id;
    return 0;
}
int dhdGetDeviceID(void) { return g_cur; }

/* ---------------------------------------------------------------------- what the device is */
int dhdGetSystemType(char id) {
    volatile double *b = dev(id);
    return b ? (int)b[B_MODEL_ID] : -1;
}
const char *dhdGetSystemName(char id) {
    volatile double *b = dev(id);
    const struct emu_fd_model *m = b ? model_of(b) : NULL;
    return m ? m->name : NULL;
}
int dhdGetSerialNumber(unsigned short *sn, char id) {
    volatile double *b = dev(id);
    if (!b) return -1;
    if (!sn) return fail(DHD_ERROR_NULL_ARGUMENT);
    *sn = (unsigned short)b[B_SERIAL];
    return 0;
}
static int has(char id, int what) {
    volatile double *b = dev(id);
    const struct emu_fd_model *m = b ? model_of(b) : NULL;
    if (!m) return 0;
    switch (what) {
    case 0: return m->sensed_rotation;
    case 1: return m->actuated_rotation;
    case 2: return m->sensed_gripper;
    case 3: return m->actuated_gripper;
    default: return 1;
    }
}
_Bool dhdHasWrist(char id) { return has(id, 0); }
_Bool dhdHasActiveWrist(char id) { return has(id, 1); }
_Bool dhdHasGripper(char id) { return has(id, 2); }
_Bool dhdHasActiveGripper(char id) { return has(id, 3); }
_Bool dhdHasBase(char id) { return has(id, 4); }
double dhdGetMaxForce(char id) {
    volatile double *b = dev(id);
    const struct emu_fd_model *m = b ? model_of(b) : NULL;
    return m ? m->max_force_n : -1.0;
}
double dhdGetMaxTorque(char id) {
    volatile double *b = dev(id);
    const struct emu_fd_model *m = b ? model_of(b) : NULL;
    return m ? m->max_torque_n_m : -1.0;
}
double dhdGetMaxGripperForce(char id) {
    volatile double *b = dev(id);
    const struct emu_fd_model *m = b ? model_of(b) : NULL;
    return m ? m->max_gripper_force_n : -1.0;
}
double dhdGetComFreq(char id) {
    volatile double *b = dev(id);
    return b && b[B_PERIOD_S] > 0 ? 1e-3 / b[B_PERIOD_S] : 0.0;  /* kHz, as the SDK reports it */
}
int dhdGetButton(int index, char id) {
    volatile double *b = dev(id);
    if (!b) return -1;
    double s[B_STATE_LAST - B_STATE_FIRST + 1];
    sample(b, s);
    return (((long)S(B_BUTTONS)) >> index) & 1;
}
unsigned int dhdGetButtonMask(char id) {
    volatile double *b = dev(id);
    if (!b) return 0;
    double s[B_STATE_LAST - B_STATE_FIRST + 1];
    sample(b, s);
    return (unsigned int)S(B_BUTTONS);
}
int dhdGetStatus(int status[DHD_MAX_STATUS], char id) {
    if (!status) return fail(DHD_ERROR_NULL_ARGUMENT);
    volatile double *b = dev(id);
    memset(status, 0, sizeof(int) * DHD_MAX_STATUS);
    if (!b) return -1;
    status[0] = 1;                              /* POWER */
    status[1] = 1;                              /* CONNECTED */
    status[2] = 1;                              /* STARTED */
    status[5] = b[B_FORCE_ON] != 0.0;           /* FORCE */
    status[9] = 0;                              /* ERROR */
    status[10] = 1;                             /* GRAVITY */
    status[14] = (int)b[B_FORCE_OFF_CAUSE];     /* FORCEOFFCAUSE */
    return 0;
}

/* ---------------------------------------------------------------------- state */
int dhdGetPosition(double *px, double *py, double *pz, char id) {
    volatile double *b = dev(id);
    if (!b) return -1;
    double s[B_STATE_LAST - B_STATE_FIRST + 1];
    sample(b, s);
    *px = S(B_POS_M); *py = S(B_POS_M + 1); *pz = S(B_POS_M + 2);
    return 0;
}
int dhdGetLinearVelocity(double *vx, double *vy, double *vz, char id) {
    volatile double *b = dev(id);
    if (!b) return -1;
    double s[B_STATE_LAST - B_STATE_FIRST + 1];
    sample(b, s);
    *vx = S(B_VEL_M_S); *vy = S(B_VEL_M_S + 1); *vz = S(B_VEL_M_S + 2);
    return 0;
}
int dhdGetAngularVelocityRad(double *wx, double *wy, double *wz, char id) {
    volatile double *b = dev(id);
    if (!b) return -1;
    const struct emu_fd_model *m = model_of(b);
    double s[B_STATE_LAST - B_STATE_FIRST + 1];
    sample(b, s);
    int rot = m && m->sensed_rotation;
    *wx = rot ? S(B_ANGVEL_RAD_S) : 0.0; *wy = rot ? S(B_ANGVEL_RAD_S + 1) : 0.0; *wz = rot ? S(B_ANGVEL_RAD_S + 2) : 0.0;
    return 0;
}
static void frame_of(const double *s, int rot, double *r) {
    double w = S(B_QUAT), x = S(B_QUAT + 1), y = S(B_QUAT + 2), z = S(B_QUAT + 3);
    if (!rot) { w = 1.0; x = y = z = 0.0; }  /* a device without a wrist reports the identity */
    r[0] = 1 - 2 * (y * y + z * z); r[1] = 2 * (x * y - w * z);     r[2] = 2 * (x * z + w * y);
    r[3] = 2 * (x * y + w * z);     r[4] = 1 - 2 * (x * x + z * z); r[5] = 2 * (y * z - w * x);
    r[6] = 2 * (x * z - w * y);     r[7] = 2 * (y * z + w * x);     r[8] = 1 - 2 * (x * x + y * y);
}
int dhdGetOrientationFrame(double matrix[3][3], char id) {
    volatile double *b = dev(id);
    if (!b) return -1;
    const struct emu_fd_model *m = model_of(b);
    double s[B_STATE_LAST - B_STATE_FIRST + 1];
    sample(b, s);
    frame_of(s, m && m->sensed_rotation, &matrix[0][0]);
    return 0;
}
int dhdGetPositionAndOrientationFrame(double *px, double *py, double *pz, double matrix[3][3], char id) {
    volatile double *b = dev(id);
    if (!b) return -1;
    const struct emu_fd_model *m = model_of(b);
    double s[B_STATE_LAST - B_STATE_FIRST + 1];
    sample(b, s);
    *px = S(B_POS_M); *py = S(B_POS_M + 1); *pz = S(B_POS_M + 2);
    frame_of(s, m && m->sensed_rotation, &matrix[0][0]);
    return 0;
}
int dhdGetOrientationRad(double *oa, double *ob, double *og, char id) {
    /* the wrist's joint angles; the emulated wrist is a spherical joint: its XYZ Euler angles */
    volatile double *b = dev(id);
    if (!b) return -1;
    const struct emu_fd_model *m = model_of(b);
    double s[B_STATE_LAST - B_STATE_FIRST + 1], r[9];
    sample(b, s);
    frame_of(s, m && m->sensed_rotation, r);
    *ob = asin(fmax(-1.0, fmin(1.0, r[2])));
    *oa = atan2(-r[5], r[8]);
    *og = atan2(-r[1], r[0]);
    return 0;
}
int dhdGetGripperAngleRad(double *a, char id) {
    volatile double *b = dev(id);
    if (!b) return -1;
    const struct emu_fd_model *m = model_of(b);
    if (!m || !m->sensed_gripper) return fail(DHD_ERROR_NOT_AVAILABLE);
    double s[B_STATE_LAST - B_STATE_FIRST + 1];
    sample(b, s);
    *a = S(B_GRIPPER_RAD);
    return 0;
}
int dhdGetGripperAngularVelocityRad(double *w, char id) {
    volatile double *b = dev(id);
    if (!b) return -1;
    const struct emu_fd_model *m = model_of(b);
    if (!m || !m->sensed_gripper) return fail(DHD_ERROR_NOT_AVAILABLE);
    double s[B_STATE_LAST - B_STATE_FIRST + 1];
    sample(b, s);
    *w = S(B_GRIPPER_RAD_S);
    return 0;
}

/* ---------------------------------------------------------------------- commands */
static int command(char id, double fx, double fy, double fz, double tx, double ty, double tz, double fg) {
    volatile double *b = dev(id);
    if (!b) return -1;
    const struct emu_fd_model *m = model_of(b);
    double c[7] = {fx, fy, fz, tx, ty, tz, fg};
    for (int k = 0; k < 7; k++) b[B_CMD + k] = c[k];
    atomic_thread_fence(memory_order_release);
    b[B_CMD_SEQ] += 1.0;
    double f = sqrt(fx * fx + fy * fy + fz * fz);
    g_err = 0;
    return m && f > m->max_force_n ? DHD_MOTOR_SATURATED : 0;
}
int dhdSetForce(double fx, double fy, double fz, char id) { return command(id, fx, fy, fz, 0, 0, 0, 0); }
int dhdSetForceAndTorque(double fx, double fy, double fz, double tx, double ty, double tz, char id) {
    return command(id, fx, fy, fz, tx, ty, tz, 0);
}
int dhdSetForceAndGripperForce(double fx, double fy, double fz, double fg, char id) {
    return command(id, fx, fy, fz, 0, 0, 0, fg);
}
int dhdSetForceAndTorqueAndGripperForce(double fx, double fy, double fz, double tx, double ty, double tz,
                                        double fg, char id) {
    return command(id, fx, fy, fz, tx, ty, tz, fg);
}
int dhdEnableForce(_Bool on, char id) {
    volatile double *b = dev(id);
    if (!b) return -1;
    b[B_FORCE_ON] = on ? 1.0 : 0.0;
    if (on) b[B_FORCE_OFF_CAUSE] = 0.0;
    else b[B_FORCE_OFF_CAUSE] = 4.0;
    return 0;
}
int dhdSetWatchdog(unsigned char units, char id) {
    volatile double *b = dev(id);
    if (!b) return -1;
    if (!g_expert) return fail(DHD_ERROR_EXPERT_MODE_DISABLED);
    b[B_WATCHDOG_S] = units * 125e-6;
    return 0;
}
int dhdGetWatchdog(unsigned char *units, char id) {
    volatile double *b = dev(id);
    if (!b) return -1;
    if (!g_expert) return fail(DHD_ERROR_EXPERT_MODE_DISABLED);
    *units = (unsigned char)lround(b[B_WATCHDOG_S] / 125e-6);
    return 0;
}
int dhdSetGravityCompensation(_Bool on, char id) { return dev(id) ? 0 : -1; }
int dhdSetBrakes(_Bool on, char id) { return dev(id) ? 0 : -1; }
int dhdEmulateButton(_Bool on, char id) { return dev(id) ? 0 : -1; }

/* ---------------------------------------------------------------------- drd: calibration */
int drdOpen(void) { return dhdOpen(); }
int drdOpenID(char id) { return dhdOpenID(id); }
int drdClose(char id) { return dhdClose(id); }
int drdSetDevice(char id) { return dhdSetDevice(id); }
_Bool drdIsSupported(char id) { return dev(id) != NULL; }
_Bool drdIsInitialized(char id) {
    volatile double *b = dev(id);
    return b && b[B_CALIBRATED] != 0.0;
}
int drdAutoInit(char id) {
    /* the real SDK drives the device through its workspace to find its encoders' references
     * (the handle moves by itself: the user must let go); here the block is marked calibrated */
    volatile double *b = dev(id);
    if (!b) return -1;
    b[B_CALIBRATED] = 1.0;
    return 0;
}
int drdCheckInit(char id) { return drdAutoInit(id); }
int drdPrecisionInit(char id) { return drdAutoInit(id); }
_Bool drdIsRunning(char id) { return 0; }
int drdStart(char id) { return fail(DHD_ERROR_NOT_IMPLEMENTED); }
int drdStop(_Bool frc, char id) { return dev(id) ? 0 : -1; }

/* the stubs (emu_stubs.c) report through this */
void emu_drd_set_error(int e) { g_err = e; }

/* the test fixture's hook (not an SDK symbol): forget the devices and read
 * $HAPTICPROXY_EMU_BLOCKS again (one process builds many emulated devices in turn) */
void emu_drd_reattach(void) {
    for (int i = 0; i < g_ndev; i++) {
        if (g_open[i]) g_blk[i][B_OWNER_PID] = 0.0;
        munmap((void *)g_blk[i], 8 * B_NSLOTS);
        g_blk[i] = NULL;
        g_open[i] = 0;
    }
    g_ndev = -1;
    g_cur = -1;
    g_expert = 0;
    g_err = 0;
    attach();
}
