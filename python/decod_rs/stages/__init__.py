"""The stages of ``decod run`` (paper Alg. 1), in the order :mod:`decod_rs.pipeline` calls
them: :mod:`~decod_rs.stages.extract` -> :mod:`~decod_rs.stages.match` (match and select)
-> :mod:`~decod_rs.stages.solve` (optimise) -> :mod:`~decod_rs.stages.refine` (the rebuilt
round, where needed) -> :mod:`~decod_rs.stages.survey` (``--survey``) ->
:mod:`~decod_rs.stages.write`."""
