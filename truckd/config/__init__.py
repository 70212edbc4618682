"""The top configuration layer: :mod:`truckd.config.truck` assembles every package's section.

Each package (model, control, io, runtime, sim) declares its own frozen dataclass section
with :func:`truckd.schema.spec`; the schema (:mod:`truckd.schema`, :mod:`truckd.yamlsafe`)
is the bottom layer and imports no truckd package.  Nothing below this package imports it
(``tests/test_layering.py``).
"""
