"""Helpers the tests and the benchmarks share, kept out of the shipped package (the car
needs none of them): synthetic plant logs (:mod:`labkit.synth`) and the decoders' mutation
fuzzing (:mod:`labkit.fuzz`).  Tests import them with ``tests/`` on the path (pytest's
``pythonpath``); benchmarks put ``tests/`` on ``sys.path`` first."""
