"""Simulated plant, simulated firmware and scenarios (stand-ins for the hardware)."""
