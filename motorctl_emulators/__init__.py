"""The gantry I/O emulator: the device side of each bus driver, for tests, benchmarks and trials.

* :mod:`~motorctl_emulators.plant_bank`: the emulated axes (the sim driver's plant, a command
  watchdog, a fault schedule), loaded from a simulated-gantry config.
* :mod:`~motorctl_emulators.device`: the device base class, the ``motorctl.emulators`` entry
  points (transport name → device class) and :func:`~motorctl_emulators.device.build_device`.
* :mod:`~motorctl_emulators.can_device`, :mod:`~motorctl_emulators.serial_device`,
  :mod:`~motorctl_emulators.modbus_device`, :mod:`~motorctl_emulators.cia402_device` (CiA 402
  drives on canopen's ``LocalNode``): the devices; :mod:`~motorctl_emulators.stream`:
  the device end of a byte stream (TCP listener or pty).
* :mod:`~motorctl_emulators.cli`: ``motorctl emulate``; :mod:`~motorctl_emulators.loopback`:
  driver and emulator as processes on one machine (benchmarks, trials; the tests reach it
  through their own, uninstalled ``tests/harness.py``).

This package uses ``motorctl`` and ``motorctl_drivers`` (codecs, frame layouts); neither of
them imports it.
"""
