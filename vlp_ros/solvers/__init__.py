"""Camera pose from observed lamps: closed forms, refinement, disambiguation, fusion."""
