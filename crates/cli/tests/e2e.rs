//! The end-to-end tests of the `tessera` binary, in one test binary: each file below is a module
//! named as the file, and `common/` the helpers they share. Run one suite with
//! `cargo test -p tessera-cli --test e2e dashboard_e2e::`.

#[path = "common/mod.rs"]
mod common;

#[path = "blender_e2e.rs"]
mod blender_e2e;
#[path = "dashboard_e2e.rs"]
mod dashboard_e2e;
#[path = "deploy_e2e.rs"]
mod deploy_e2e;
#[path = "docs_e2e.rs"]
mod docs_e2e;
#[path = "farm_doors_e2e.rs"]
mod farm_doors_e2e;
#[path = "farm_e2e.rs"]
mod farm_e2e;
#[path = "quality_e2e.rs"]
mod quality_e2e;
#[path = "refine_e2e.rs"]
mod refine_e2e;
#[path = "render_e2e.rs"]
mod render_e2e;
#[path = "steer_e2e.rs"]
mod steer_e2e;
