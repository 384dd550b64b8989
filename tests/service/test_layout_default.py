"""``processes = -1`` (the default): which layout ``rlutf serve`` runs where."""

from __future__ import annotations

from service.config import Settings


def test_one_process_per_usable_core_in_router_mode() -> None:
    s = Settings()
    assert s.processes == -1
    assert s.service_processes(cores=2) == 2
    assert s.service_processes(cores=8) == 8
    assert s.service_processes(cores=1) == 0  # nothing to spread: no host in front


def test_the_layout_of_workers_where_it_is_what_serves() -> None:
    assert Settings(mode="client").service_processes(cores=4) == 0  # a fleet's instance
    assert Settings(mode="peer").service_processes(cores=4) == 0
    assert Settings(foxglove_port=8765).service_processes(cores=4) == 0  # a live view
    assert Settings(workers=2).service_processes(cores=4) == 0  # workers asked for
    assert Settings(workers=-1).service_processes(cores=4) == 0  # even "one per core"


def test_an_explicit_count_is_kept() -> None:
    assert Settings(processes=0).service_processes(cores=4) == 0
    assert Settings(processes=3).service_processes(cores=1) == 3
    assert Settings(processes=2, mode="client").service_processes(cores=8) == 2
