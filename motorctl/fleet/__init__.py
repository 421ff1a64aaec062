"""A fleet's health from its run logs: identification over many machines' logs on Dask
(:mod:`motorctl.fleet.jobs`), the report of each parameter over time with its trend, change
points and the fleet's spread (:mod:`motorctl.fleet.report`), and a simulated fleet with
injected wear for tests and the benchmark (:mod:`motorctl.fleet.simulate`).

dask, distributed, pyarrow and fsspec (the ``fleet`` extra) are imported inside the functions
that use them, so that importing this package costs nothing and a missing extra is one line
naming it (``motorctl.cli``). The tour: docs/fleet.md.
"""
