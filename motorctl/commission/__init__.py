"""Commissioning: autotune (measure, fit, choose, verify), tune, the closed-loop
before/after of identify, run-log comparison and the laws' loop shapes. Imports the runtime
(:mod:`motorctl.app`), never the reverse."""
