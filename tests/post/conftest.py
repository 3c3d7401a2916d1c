"""Fixtures of the post-processing tests."""

import pytest

from stereodem.post import coreg_figures, figures, product_figures
from stereodem.sensor.estimation import compare


@pytest.fixture
def captured(monkeypatch):
    """Figures as drawn, just before they are saved (every figure module's saving path)."""
    figs = []

    def keep(save):
        def wrapped(fig, *a, **k):
            figs.append(fig)
            return save(fig, *a, **k)

        return wrapped

    monkeypatch.setattr(figures, "_save", keep(figures._save))
    monkeypatch.setattr(coreg_figures, "_save", keep(coreg_figures._save))
    monkeypatch.setattr(product_figures, "_save", keep(product_figures._save))
    monkeypatch.setattr(compare, "save_png", keep(compare.save_png))
    return figs
