"""Fixtures of the kit tests."""

import threading

import pytest
from helpers import free_port


@pytest.fixture
def router():
    """A Zenoh router in this process for `octolog run --router`, so a test peer can join the run."""
    from octolog.kit.bus import serve_router

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    stop, ready = threading.Event(), threading.Event()
    thread = threading.Thread(target=serve_router, args=((endpoint,),), kwargs={"stop": stop, "ready": ready.set},
                              daemon=True)
    thread.start()
    assert ready.wait(30)
    yield endpoint
    stop.set()
    thread.join(timeout=30)
