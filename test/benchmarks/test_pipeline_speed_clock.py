"""pipeline_speed's CPU clock leaves out time the benchmark spends without a core."""
import time

from vlp_ros.benchmarks.pipeline_speed import CLOCKS, interleaved_times


def test_cpu_clock_does_not_count_waiting_and_wall_clock_does() -> None:
    runs = {'wait': lambda _: time.sleep(0.02)}
    wall = interleaved_times(runs, repeats=3, warmup=0, clock=CLOCKS['wall'])['wait']
    cpu = interleaved_times(runs, repeats=3, warmup=0, clock=CLOCKS['cpu'])['wait']
    assert min(wall) >= 0.02
    assert max(cpu) < 0.005
