"""The study beside the library: the commands that run and summarise many trainings, built on the
library's public names only (``tests/study/test_study_boundary.py`` checks it).

- the scale study, ``taskvar experiment scale`` (docs/scale.md): :mod:`~taskvar_torch.study.scale`
  (the protocol, the loader), ``scale_config`` (the cases and each cell's config), ``scale_eval``
  (evaluation, references), ``scale_cell`` (one cell), ``scale_report`` (table, CSV, figures);
- ``taskvar report`` (docs/report.md): :mod:`~taskvar_torch.study.report` (the pages),
  ``report_folders`` (the results folders read and grouped), ``report_claims`` (the paper's
  claims scored), ``report_results`` (the Results tables), ``aggregate`` (rliable's statistics);
- ``taskvar sweep`` (docs/sweeps.md): :mod:`~taskvar_torch.study.sweep` (the backends),
  ``sweep_grid`` (points, configs, resume, summary), ``sweep_jobs`` (what a worker runs).

The library (``taskvar_torch`` outside this package) imports nothing from it; the command line
(``cli.py``) and the experiment registry (``scale``, by module name) dispatch to it.
"""
