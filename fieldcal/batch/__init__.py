"""Fleets: many stacks or lenses, one task each, on Dask distributed (the optional extra ``fieldcal[dask]``).

* :mod:`fieldcal.batch.engine` — the only module that imports Dask: a LocalCluster or an existing scheduler,
  one task per unit, progress as units finish, a failed unit reported and the rest finished
  (:func:`~fieldcal.batch.engine.run_units`);
* :mod:`fieldcal.batch.calibrate` — ``fieldcal batch calibrate``'s unit: one stack → one profile;
* :mod:`fieldcal.batch.lenses` — ``fieldcal validate --lenses N``'s unit: one random simulated lens → one
  validation report;
* :mod:`fieldcal.batch.fleet` — the ``fieldcal-fleet/1`` report: the spread of the units' surfaces and
  tolerances and the units that differ from the fleet.

See docs/batch.md (how to point it at a cluster).
"""
