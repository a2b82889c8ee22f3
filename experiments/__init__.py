"""The paper's experiments, reproduced on the simulated arm, and the ones beyond it.

Each experiment is a module of this package registered in :mod:`experiments.registry`; one run
writes a folder ``<out>/<name>/`` with

- ``result.json`` -- an :class:`experiments.result.ExperimentResult`: the configuration and seed,
  the tables of every metric (with units), the headline figures and the list of plots;
- ``*.png`` -- the plots, named in ``result.json``;
- ``*.mcap`` -- the runs' trajectories (when the experiment records any), openable in Foxglove
  and by ``psm report``.

``psm experiments NAME|--all`` runs them; ``psm report`` turns result folders (or a recording)
into one Markdown and one HTML report.
"""
