//! The coordinator's probes over plain HTTP (`--metrics ADDR`): `GET /metrics` (Prometheus text
//! format), `/healthz` (the process answers and its state is sound, without waiting for the
//! state lock) and `/readyz` (it is serving gRPC: false before the listener is up and once
//! shutdown has begun, so a load balancer stops sending clients).

use crate::core::FarmMetrics;
use crate::engine::Engine;
use crate::leases::Ignored;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use tessera_proto::probe::{self, Page};

pub async fn serve(listener: tokio::net::TcpListener, engine: Arc<Engine>) {
    probe::serve(listener, Arc::new(move |path: &str| page(&engine, path))).await
}

fn page(engine: &Engine, path: &str) -> Page {
    match path {
        "/metrics" => match engine.with(|c| Ok(c.farm_metrics())) {
            Ok(f) => Page::ok(prometheus(&f) + &notifications(engine)),
            Err(e) => Page { code: 500, body: e.to_string() },
        },
        "/healthz" => match engine.healthy() {
            Ok(()) => Page::ok("ok\n"),
            Err(e) => Page { code: 500, body: format!("{e}\n") },
        },
        "/readyz" if engine.serving.load(Ordering::Relaxed) => Page::ok("ready\n"),
        "/readyz" => Page::unavailable("not serving (starting or shutting down)\n"),
        _ => Page::not_found(),
    }
}

/// The notifier's counters (none without `--notify-key`).
fn notifications(engine: &Engine) -> String {
    let Some(n) = &engine.notifier else { return String::new() };
    let mut out = String::new();
    for (name, help, value) in [
        ("tessera_notifications_sent_total", "Notifications delivered (a 2xx answer).", &n.counts.sent),
        ("tessera_notifications_failed_total", "Notifications given up after retrying.", &n.counts.failed),
        ("tessera_notifications_dropped_total", "Notifications dropped: too many were waiting.", &n.counts.dropped),
    ] {
        let value = value.load(Ordering::Relaxed);
        out += &format!("# HELP {name} {help}\n# TYPE {name} counter\n{name} {value}\n");
    }
    out
}

/// The farm's numbers in Prometheus's text exposition format.
pub fn prometheus(f: &FarmMetrics) -> String {
    let m = &f.counters;
    let rows: [(&str, &str, &str, f64); 18] = [
        (
            "tessera_passes_in_flight",
            "gauge",
            "Passes leased to workers and not yet merged.",
            f.passes_in_flight as f64,
        ),
        (
            "tessera_pending_passes",
            "gauge",
            "Passes scheduled and not yet leased or merged, over all renders.",
            f.pending_passes as f64,
        ),
        ("tessera_passes_leased_total", "counter", "Passes handed to workers.", f.passes_leased as f64),
        ("tessera_passes_completed_total", "counter", "Passes merged.", m.passes_merged as f64),
        ("tessera_passes_expired_total", "counter", "Passes whose lease expired.", f.passes_expired as f64),
        (
            "tessera_passes_released_total",
            "counter",
            "Passes handed back unrendered by workers shutting down.",
            f.passes_released as f64,
        ),
        (
            "tessera_pending_frames",
            "gauge",
            "Frames of sequences not finished yet (queued or rendering).",
            f.pending_frames as f64,
        ),
        ("tessera_workers_alive", "gauge", "Workers seen within two lease times.", f.workers_alive as f64),
        ("tessera_renders_running", "gauge", "Renders in progress.", f.renders_running as f64),
        ("tessera_samples_merged_total", "counter", "Samples merged.", m.samples_merged as f64),
        (
            "tessera_samples_per_second",
            "gauge",
            "Samples merged per second since start.",
            m.samples_merged as f64 / f.uptime_seconds.max(1e-3),
        ),
        ("tessera_bytes_in_total", "counter", "Scene and result bytes received.", m.bytes_in as f64),
        ("tessera_bytes_out_total", "counter", "Scene and image bytes sent.", m.bytes_out as f64),
        (
            "tessera_results_checked_total",
            "counter",
            "Results rendered again by a second or third worker and compared (--verify).",
            m.results_checked as f64,
        ),
        (
            "tessera_results_disputed_total",
            "counter",
            "Checks whose sums disagreed with the result they checked: a third worker decided.",
            m.results_disputed as f64,
        ),
        (
            "tessera_checks_pending",
            "gauge",
            "Merged results waiting to be checked by another worker; their renders finish after.",
            f.checks_pending as f64,
        ),
        (
            "tessera_workers_blocked",
            "gauge",
            "Workers blocked for the farm because their results disagreed with two other workers'.",
            f.workers_blocked as f64,
        ),
        (
            "tessera_merge_seconds_total",
            "counter",
            "Time spent validating, storing and merging results.",
            m.merge_seconds_total,
        ),
    ];
    let mut out = String::new();
    for (name, kind, help, value) in rows {
        out += &format!("# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {value}\n");
    }
    out += "# HELP tessera_results_ignored_total Results ignored, by reason (duplicate, late, released, render_ended, wrong_worker, unknown_lease, blocked_worker).\n# TYPE tessera_results_ignored_total counter\n";
    for why in Ignored::ALL {
        let n = m.results_ignored.get(&why).copied().unwrap_or(0);
        out += &format!("tessera_results_ignored_total{{reason=\"{}\"}} {n}\n", why.label());
    }
    out += &format!(
        "# HELP tessera_merges_total Results merged.\n# TYPE tessera_merges_total counter\ntessera_merges_total {}\n",
        m.merges
    );
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::CoreConfig;

    #[test]
    fn healthz_answers_while_the_core_is_busy() {
        let dir = tempfile::Builder::new().prefix("tessera-healthz-").tempdir().unwrap();
        let shared = Engine::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
        let (locked_tx, locked_rx) = std::sync::mpsc::channel();
        let (release_tx, release_rx) = std::sync::mpsc::channel::<()>();
        let busy = shared.clone();
        let holder = std::thread::spawn(move || {
            busy.with(|_| {
                locked_tx.send(()).unwrap();
                release_rx.recv().unwrap();
                Ok(())
            })
        });
        locked_rx.recv().unwrap();
        // The lock is held until we say so: a /healthz that waited on it would never return.
        let (tx, rx) = std::sync::mpsc::channel();
        let probe = shared.clone();
        std::thread::spawn(move || tx.send(page(&probe, "/healthz").code).unwrap());
        let code = rx.recv_timeout(std::time::Duration::from_secs(10));
        release_tx.send(()).unwrap();
        holder.join().unwrap().unwrap();
        assert_eq!(code, Ok(200), "/healthz waited on the core lock");
    }
}
