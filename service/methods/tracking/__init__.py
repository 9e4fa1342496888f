"""Performance-flow tracking (fyffe et al., Digital Ira course 2014, "Driving High-Resolution
Facial Scans with Video Performance Capture", §4–5): video + static scans → a drift-free
tracked sequence on the artist mesh, per-frame scan weights and blended maps.

Modules: :mod:`.params` (the one parameter model), :mod:`.regions` (the facial regions of
§4.1), :mod:`.graph` (the performance flow graph, §4–4.1), :mod:`.solve` (the coupled
tracking energy, §5.2–5.6), :mod:`.track` (keyframes then spans, §5.7; the pipeline),
:mod:`.maps` (per-frame scan weights and blended maps, §7.3).
"""
