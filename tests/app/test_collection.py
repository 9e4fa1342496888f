"""The cyclic collector paused while ``serve`` starts (service.app.collection)."""

import gc
import threading

import pytest

from service.app.collection import pause_collection, resume_when


@pytest.fixture(autouse=True)
def collector_restored():
    enabled = gc.isenabled()
    yield
    (gc.enable if enabled else gc.disable)()


def test_pause_then_resume_restores_the_collector():
    gc.enable()
    resume = pause_collection()
    assert not gc.isenabled()
    resume()
    assert gc.isenabled()
    gc.disable()
    resume()            # idempotent: a second call does not turn it on again
    assert not gc.isenabled()


def test_a_collector_that_was_off_stays_off():
    gc.disable()
    resume = pause_collection()
    resume()
    assert not gc.isenabled()


def test_resume_when_waits_for_the_event():
    gc.enable()
    resume = pause_collection()
    done = threading.Event()
    resumed = threading.Event()

    def resume_and_note() -> None:
        resume()
        resumed.set()

    resume_when(resume_and_note, done)
    assert not resumed.wait(0.05) and not gc.isenabled()
    done.set()
    assert resumed.wait(5) and gc.isenabled()


def test_resume_when_without_an_event_resumes_at_once():
    gc.enable()
    resume = pause_collection()
    resume_when(resume, None)
    assert gc.isenabled()
