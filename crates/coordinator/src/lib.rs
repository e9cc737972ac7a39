//! The coordinator: `core` is its synchronous state machine (renders and sequences planned by
//! `tessera_render::plan`, the lease table that hands passes out, takes them back when leases
//! expire and accepts each pass at most once); no tokio, no sockets. The gRPC shell (`service.rs`,
//! `server.rs`, `connections.rs`) validates, converts and calls into it. `store` keeps the
//! durable state in SQLite.

pub mod connections;
pub mod core;
pub mod dashboard;
pub mod leases;
pub mod metrics;
pub mod model;
pub mod server;
pub mod service;
pub mod store;
pub mod users;
pub mod wire;

pub use leases::{Completion, JobLease, LeaseTable};
pub use store::{Store, StoreError, StoredRender, StoredResult};

pub use core::{Core, CoreConfig, CoreError};
pub use server::{MAX_CONNECTIONS, Tokens, listen, serve};
pub use service::Shared;
