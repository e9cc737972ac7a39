//! The gRPC door: the render and work services (`service.rs`), their listener and token check
//! (`server.rs`), and the conversions between protobuf and the core's types (`wire.rs`). Only
//! this door and the worker and CLI know the protocol's messages.

pub mod server;
pub mod service;
pub mod wire;
