"""What a simulated scan can be asked for, in a module that imports neither trimesh nor SciPy: the
command line checks and shows these choices without loading the scanner."""

# Length units a model may come in, as multiples of a metre (guessed from a head's size).
UNITS_PER_METRE = {"m": 1.0, "cm": 100.0, "mm": 1000.0}
# ... and a scan: scanner software exports inches too.
SCAN_UNITS_PER_METRE = {**UNITS_PER_METRE, "in": 100.0 / 2.54}
# What clutter a realistic scan can hold: hair over the scalp, a neck and shoulders tube below.
CLUTTER_PARTS = ("hair", "neck")
