"""ngp-mi doctor: versions, backend and a test render."""

from helpers import run_cli


def test_doctor_reports_and_renders():
    done = run_cli("doctor")
    assert done.returncode == 0, done.stdout + done.stderr
    for key in ("python", "torch", "mitsuba   3.9.1", "drjit     1.5.0", "variant", "libLLVM", "threads", "64x64 ok"):
        assert key in done.stdout
