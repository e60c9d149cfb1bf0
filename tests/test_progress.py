"""Warnings reach stderr whatever silences progress (a doubtful result must never pass unseen)."""

from fieldcal.progress import status, warn


def test_warning_printed_when_progress_is_silenced(monkeypatch, capsys):
    monkeypatch.setenv("FIELDCAL_PROGRESS", "0")
    status("a status line")
    warn("the scan does not bracket the centre")
    err = capsys.readouterr().err
    assert "a status line" not in err  # progress/status are silenced ...
    assert "warning: the scan does not bracket the centre" in err  # ... warnings are not


def test_status_printed_when_enabled_and_hidden_when_quiet(monkeypatch, capsys):
    monkeypatch.setenv("FIELDCAL_PROGRESS", "1")
    status("shown")
    status("hidden", quiet=True)
    err = capsys.readouterr().err
    assert "shown" in err and "hidden" not in err
