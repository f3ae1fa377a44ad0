"""Simulation environments, one folder per benchmark."""
