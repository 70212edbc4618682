"""Control: state estimation, warm-started OSQP MPC, friction feedforward, fallback.

Pure numerics: plain data in, command and diagnostics out, time passed in.
"""
