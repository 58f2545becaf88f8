"""Registration pipelines tried as the default beside the shipped methods, shared by the studies
that measure them (held_out_half.py, cross_family.py, cross_family_landmarks.py; docs/studies.md §19).

A name maps to (stages, register options). "closed form σ s" is the default's first stage (the
Gauss–Newton pca stage without the landmark term) with the prior's noise s (shipped: 0.003).
"""
from __future__ import annotations


def candidates() -> dict:
    from statfit.core.settings import Settings

    def closed_form(noise: float) -> Settings:
        return Settings("pca", 200, 0.0, optimizer="gauss-newton", noise=noise, landmarks=False)

    tried = {}
    for noise in (0.003, 0.01, 0.03):
        tried[f"closed form σ {noise} → laplacian λ 300 lr 0.03 300 it"] = (
            (closed_form(noise), Settings("laplacian", 300, 0.03, lam=300.0)), {})
        if noise != 0.003:
            tried[f"closed form σ {noise} → hybrid β 1 lr 0.03 200 it"] = (
                (closed_form(noise), Settings("hybrid", 200, 0.03, beta=1.0, lam=19.0)), {})
    return tried


def register_candidate(method: str, model, points, tried: dict | None = None, **options):
    """``register`` with a shipped method or pipeline, or a candidate of ``tried`` (name → (stages,
    options); default :func:`candidates`). A candidate without stages is a shipped method with
    options, named "<method> w <landmark weight>"."""
    from statfit.registration.job import register

    stages, extra = (candidates() if tried is None else tried).get(method, (None, {}))
    shipped = method.split(" w ")[0] if stages is None else "default"
    return register(model, points, shipped, stages=stages, **options, **extra)
