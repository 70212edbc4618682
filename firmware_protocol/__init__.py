"""The firmware protocol: truck.dbc and the codecs, framing and checks built on it."""
