"""The bus layer: typed messages over Eclipse Zenoh, the service skeleton, MCAP recorder/replayer.

Modules: :mod:`~services.bus.messages` (catalogue of types, keys, encodings, QoS),
:mod:`~services.bus.config` (typed config: pydantic-settings, stack files),
:mod:`~services.bus.runtime` (sessions, the ``Service`` and the ``ServiceApp`` skeleton run by
``run_service``), :mod:`~services.bus.errors` (``BusError``), :mod:`~services.bus.recorder`,
:mod:`~services.bus.replayer`, :mod:`~services.bus.log` (``read_log``),
:mod:`~services.bus.echo`, :mod:`~services.bus.introspect` (``psm status``, ``psm topics``),
:mod:`~services.bus.router`, :mod:`~services.bus.cli`. See ``docs/bus.md``.
"""
