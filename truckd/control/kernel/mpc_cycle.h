/* What the controller's numerics (cycle_numerics.c) call of the MPC's compiled cycle
 * (mpc_cycle.c); truckd/control/ccycle.py checks TRUCKD_MPC_ABI against its own ABI. */
#ifndef TRUCKD_MPC_CYCLE_H
#define TRUCKD_MPC_CYCLE_H

#include <stdint.h>

#define TRUCKD_MPC_ABI 7

/* One MPC cycle on the arrays bound by truckd_mpc_bind_io (see mpc_cycle.c). */
int64_t truckd_mpc_run(int64_t inst, int64_t how);

#endif
