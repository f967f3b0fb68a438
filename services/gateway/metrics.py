"""``GET /metrics``: the gateway's view in Prometheus text format (prometheus_client's
own exposition, from a collector that reads the core when scraped)."""

from __future__ import annotations

from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, SummaryMetricFamily
from prometheus_client.registry import CollectorRegistry

import numpy as np

from semservo.protocol import HEALTH


class GatewayCollector:
    def __init__(self, core):
        self.core = core

    def collect(self):
        core = self.core
        frames = CounterMetricFamily("semservo_frames", "frames the gateway received from the image server")
        frames.add_metric([], core.counters["frames"])
        yield frames
        iterations = CounterMetricFamily("semservo_iterations", "controller iterations recorded")
        iterations.add_metric([], core.counters["iterations"])
        yield iterations
        rate = GaugeMetricFamily("semservo_frame_rate", "frames per second over the last 5 s")
        rate.add_metric([], core.frame_rate.rate(core.clock()))
        yield rate
        latencies = list(core.latencies_ms)
        latency = SummaryMetricFamily("semservo_loop_latency_seconds",
                                      "frame published -> voltage command written (last 1000 moves)")
        latency.add_metric([], count_value=len(latencies), sum_value=float(np.sum(latencies)) / 1000 if latencies else 0.0)
        yield latency
        error = GaugeMetricFamily("semservo_error_px", "translation error of the run's last fresh estimate")
        error.add_metric([], float(core.last_status.get("error_px") or 0.0))
        yield error
        up = GaugeMetricFamily("semservo_service_up", "1 when the service answers health", labels=["service"])
        dropped = CounterMetricFamily("semservo_dropped", "messages a service dropped, by reason",
                                      labels=["service", "reason"])
        for name, port in core.ports.items():
            if port is None:
                continue
            try:
                health = port.call(HEALTH)
            except Exception:  # a down service is a 0, never a failed scrape
                up.add_metric([name], 0)
                continue
            up.add_metric([name], 1)
            for key, value in health.counters.items():
                if key.startswith("dropped_"):
                    dropped.add_metric([name, key.removeprefix("dropped_")], value)
        yield up
        yield dropped


def metrics_text(core) -> tuple[bytes, str]:
    registry = CollectorRegistry(auto_describe=False)
    registry.register(GatewayCollector(core))
    return generate_latest(registry), CONTENT_TYPE_LATEST
