"""The configuration layer: :mod:`truckd.config.truck` assembles every package's section.

Each package below this one (model, control, io) declares its own frozen dataclass
section with :func:`truckd.schema.spec`; the sections of the packages above it (the
daemon's ``runtime:``, :mod:`truckd.config.runtime`, and ``characterize:``,
:mod:`truckd.config.characterize`) live here, so the configuration imports nothing of
:mod:`truckd.runtime` (which imports it).  The schema (:mod:`truckd.schema`,
:mod:`truckd.yamlsafe`) is the bottom layer and imports no truckd package.  Nothing below
this package imports it (``tests/test_layering.py``).
"""
