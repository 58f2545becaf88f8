"""The plain data every layer passes around: the unit frame, cameras, and the observations a fit
takes (a scan, a normal map, photographs). No maths beyond their own invariants, no files."""
