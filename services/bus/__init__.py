"""The bus layer: typed messages over Eclipse Zenoh, the service runtime, MCAP recorder/replayer.

Modules: :mod:`~services.bus.messages` (catalogue of types, keys, encodings, QoS),
:mod:`~services.bus.config` (typed config), :mod:`~services.bus.runtime` (sessions and the
``Service`` helper), :mod:`~services.bus.recorder`, :mod:`~services.bus.replayer`,
:mod:`~services.bus.log` (``read_log``), :mod:`~services.bus.echo`, :mod:`~services.bus.router`,
:mod:`~services.bus.cli`. See ``docs/bus.md``.
"""
