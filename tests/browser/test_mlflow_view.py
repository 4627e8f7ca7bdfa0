"""The browser check of :mod:`mlflow_view` under pytest: the link atdrone prints opens the runs table with the
population's SUC column and charts without empty sections (skipped where there is no Chromium)."""

from __future__ import annotations

import shutil

import mlflow_view
import pytest


@pytest.mark.skipif(not (shutil.which("chromium") or shutil.which("chromium-browser")), reason="no Chromium")
@pytest.mark.timeout(300)
def test_printed_link_opens_the_runs_table_with_the_suc_column(capsys: pytest.CaptureFixture[str]) -> None:
    assert mlflow_view.main([]) == 0, capsys.readouterr().err
