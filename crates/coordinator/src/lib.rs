//! The coordinator's plain, synchronous core: the planner that cuts a render into tiles and
//! passes and sizes jobs, and the lease table that hands passes out, takes them back when leases
//! expire, and accepts each pass at most once. No tokio, no sockets: the gRPC shell (`service.rs`,
//! `server.rs`, `connections.rs`) validates, converts and calls into these. `store` keeps the
//! durable state in SQLite.

pub mod connections;
pub mod core;
pub mod leases;
pub mod metrics;
pub mod planner;
pub mod server;
pub mod service;
pub mod store;
pub mod users;

pub use leases::{Completion, JobLease, LeaseTable};
pub use planner::{RenderPlan, job_passes};
pub use store::{Store, StoreError, StoredRender, StoredResult};

pub use core::{Core, CoreConfig, CoreError};
pub use server::{MAX_CONNECTIONS, Tokens, serve};
pub use service::Shared;
