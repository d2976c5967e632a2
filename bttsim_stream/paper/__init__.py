"""The paper's studies, reference benchmark and validation (Nour, Bonello et al.).

Code that reproduces the paper's numbers with the library, kept apart from the runtime:

* :mod:`.studies` -- Table 2, Table 3 / Fig. 11, ND 1 vs ND 14, Figs. 6-10, probe count
  (``bttsim study NAME --out DIR``, or ``python -m bttsim_stream.paper.studies NAME --out DIR``);
* :mod:`.bench_ref` -- a ``solve_ivp`` + event-function reference simulator in the paper's
  style and the ``bench`` study;
* :mod:`.validate_sim` -- the simulator against Sec. 3.2-3.3.1 (``bttsim validate``);
* :mod:`.validate_processing` -- the processing against Table 2, Table 3 and the ND checks
  (``bttsim validate --processing``), and :func:`~.validate_processing.simulate`, the
  per-process cache of simulated runs the studies and tests share;
* :mod:`._report` -- Markdown tables, output files and figures shared by the studies.

The runtime (simulator, processing, nodes, transport, views) never imports this package;
only the ``bttsim study`` and ``bttsim validate`` commands load it, on demand. The figures
need the ``plot`` extra (matplotlib).
"""
