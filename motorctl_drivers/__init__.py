"""The production I/O drivers of motorctl, each registered in the ``motorctl.drivers`` entry-point
group: ``sim`` (the simulated gantry), ``can`` (python-can), ``serial`` (pyserial), ``modbus``
(pymodbus framers). The bus drivers share :mod:`motorctl_drivers.split_phase`.

Nothing here imports the emulated devices (``motorctl_emulators``), and only the sim driver
itself holds the simulated plant.
"""
