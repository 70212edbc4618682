"""Configuration: typed sections, validated on load (see :mod:`truckd.config.schema`)."""
