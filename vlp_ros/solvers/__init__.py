"""Camera pose from observed lamps: closed forms, refinement, disambiguation, fusion.

Entry points: ``perspective.solve_lamp`` (one lamp: refined candidates),
``ambiguity.choose_candidate`` (a pose only on real information) and
``fusion.solve_lamps`` (every lamp of a frame, one or more). ``paper`` is the
seed paper's weak-perspective solver for comparison.
"""
