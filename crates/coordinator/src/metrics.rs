//! The coordinator's HTTP side door: `GET /metrics` (Prometheus text format), `/healthz` (the
//! process answers and its state is sound) and `/readyz` (it is serving gRPC: false before the
//! listener is up and once shutdown has begun, so a load balancer stops sending clients).

use crate::service::Shared;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use tessera_proto::probe::{self, Page};

pub async fn serve(listener: tokio::net::TcpListener, shared: Arc<Shared>) {
    probe::serve(listener, Arc::new(move |path: &str| page(&shared, path))).await
}

fn page(shared: &Shared, path: &str) -> Page {
    match path {
        "/metrics" => match shared.with(|c| Ok(c.prometheus())) {
            Ok(text) => Page::ok(text),
            Err(e) => Page { code: 500, body: e.message().to_string() },
        },
        "/healthz" => match shared.with(|_| Ok(())) {
            Ok(()) => Page::ok("ok\n"),
            Err(e) => Page { code: 500, body: format!("{}\n", e.message()) },
        },
        "/readyz" if shared.serving.load(Ordering::Relaxed) => Page::ok("ready\n"),
        "/readyz" => Page::unavailable("not serving (starting or shutting down)\n"),
        _ => Page::not_found(),
    }
}
