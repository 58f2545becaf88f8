"""Data terms: callables ``objective(vertices, iteration) -> dict[str, Tensor]`` of loss terms."""
