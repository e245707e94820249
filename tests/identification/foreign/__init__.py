"""Foreign log generators for prsa-fit (issue 32, part 6).

Simulators written without reading prsa-ctrl's fitting or model code (numpy/scipy only) that
deliberately differ from the toolkit's model structure: two-mass axes, the nut loss on the whole
force through the nut, standstill (Stribeck) friction with a Coulomb level per direction,
filtered and quantised speed, two delays, non-SI log units. Each ``gen_*.py`` module has
``generate(out_dir, seed)`` (writes logs, a measured FRF and a base plant file, returns the paths
and the truth) and ``truth()`` (SI, under the toolkit's plant keys where one exists).
"""
