"""
Camera pose from observed lamps: closed forms, refinement, disambiguation, fusion.

Entry points: ``perspective.solve_lamp`` (one lamp: refined candidates),
``ambiguity.choose_candidate`` (a pose only on real information) and
``fusion.solve_lamps`` (every lamp of a frame, one or more). An up hint with a
sigma (``ambiguity.UpHint``) also enters both fits as a measurement
(``up_measurement``). ``paper`` is the seed paper's weak-perspective solver for
comparison.
"""
