//! The coordinator, as one engine behind two doors:
//! - `core/`: the synchronous state machine (renders and sequences planned by
//!   `tessera_render::plan`, the lease table, merges, the failure policy, what views show), one
//!   verb a file; no I/O, no tokio, no protobuf or HTTP.
//! - `engine.rs`: the core behind its lock, the store's writer, reads outside the lock, image
//!   I/O; what both doors call.
//! - `grpc/`: the gRPC door (services, listener and tokens, wire conversions).
//! - `http/`: the HTTP door (dashboard, sessions and CSRF, probes and metrics).
//! - `doors.rs`: the connection limits and timers both doors share.
//! - `store/`: the durable state in SQLite, and its writer (`store/writer.rs`); `leases.rs`: the lease table;
//!   `model.rs`: the core's own types; `users.rs`: the token file.

pub mod core;
pub mod doors;
pub mod engine;
pub mod grpc;
pub mod http;
pub mod leases;
pub mod model;
pub mod store;
pub mod users;

pub use leases::{Completion, JobLease, LeaseTable};
pub use store::{Store, StoreError, StoredRender, StoredResult};

pub use core::{Core, CoreConfig, CoreError};
pub use engine::{Engine, EngineError};
pub use grpc::server::{MAX_CONNECTIONS, Tokens, listen, serve};
