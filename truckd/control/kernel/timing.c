/* OSQP's timer for its generated code (OSQP_ENABLE_PROFILING: the solve's run time and its
 * time limit, as in OSQP's own build).  The generated workspaces carry no timer object,
 * so one start time per thread serves them all: OSQP starts it at each update and solve
 * and reads it within the same call. */
#define _POSIX_C_SOURCE 199309L /* clock_gettime */
#include <time.h>

#include "osqp_configure.h"
#include "types.h"
#include "timing.h"

static __thread struct timespec started;

void osqp_tic(OSQPTimer *t) {
    (void)t;
    clock_gettime(CLOCK_MONOTONIC, &started);
}

OSQPFloat osqp_toc(OSQPTimer *t) {
    struct timespec now;
    (void)t;
    clock_gettime(CLOCK_MONOTONIC, &now);
    return (OSQPFloat)(now.tv_sec - started.tv_sec) + 1e-9 * (OSQPFloat)(now.tv_nsec - started.tv_nsec);
}
