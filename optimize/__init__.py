"""Jobs over whole rollouts (installed as ``jaxsync.optimize``), one subpackage a family:

- ``tuning``: what is tuned, the cost, the batches, the methods, the loop and the
  ``jaxsync tune`` job;
- ``studies``: the paper comparison, sweeps, sensitivities and the study of every
  controller at its own optimum (each uses ``tuning``, never the other way);
- ``benchmarks``: ``jaxsync bench`` and the tuner benchmark (they use ``tuning``).
"""
