"""The seed's truck model (thesis section 6.1): DC motor, stiff drivetrain, friction.

Pure numerics: no I/O, no clock.  The simulator, the MPC's prediction model and the
diagnosis all build on :mod:`truckd.model.params`, :mod:`truckd.model.linear` and
:mod:`truckd.model.motor`.
"""
