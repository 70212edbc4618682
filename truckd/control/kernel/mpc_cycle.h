/* What the controller's numerics (cycle_numerics.c) call of the MPC's compiled cycle
 * (mpc_cycle.c) and of the estimator (estimator.c); truckd/control/ccycle.py checks
 * TRUCKD_MPC_ABI against its own ABI. */
#ifndef TRUCKD_MPC_CYCLE_H
#define TRUCKD_MPC_CYCLE_H

#include <stdint.h>

#define TRUCKD_MPC_ABI 10

/* One MPC cycle on the arrays bound by truckd_mpc_bind_io (see mpc_cycle.c). */
int64_t truckd_mpc_run(int64_t inst, int64_t how);

/* truckd_cycle_run's status when it stopped after the estimate. */
#define TRUCKD_CYCLE_ESTIMATED (-101)

/* The estimator's update and estimate on the arrays bound by truckd_estimator_bind
 * (estimator.c): 0, or negative when the call is wrong. */
int64_t truckd_estimator_cycle(int64_t inst);

/* The estimate truckd_estimator_cycle wrote (ESTIMATE_FIELDS values). */
const double *truckd_estimator_output(int64_t inst);

/* The numerics' cycle (cycle_numerics.c). */
int64_t truckd_numerics_run(int64_t inst, int64_t how);

#endif
