"""truckd: model, controller, firmware link and diagnosis for a 1:14 model truck."""

__version__ = "0.1.0"
