//! Tessera's gRPC contract: the code tonic and prost generate from `proto/tessera/v1`, the
//! protocol version, the exact binary encoding of tile sums, token rules and the plain-HTTP
//! probe server. What a request means, and its conversion, is `tessera-request`'s.

pub mod accept;
pub mod probe;
pub mod sums;
pub mod token;

/// Generated messages and services of `tessera.v1`.
#[allow(clippy::all, missing_docs)]
pub mod v1 {
    tonic::include_proto!("tessera.v1");
}

/// The version every request carries. Bump it on any incompatible change.
/// Version 2: render settings carry the colour transport (`ColorMode`), and tile sums are
/// signed (TSUM format 3). A version-1 worker would render a spectral job in RGB: refused.
/// Version 3: settings say whether the render is transparent, and tile sums count the camera
/// rays that hit the scene (TSUM format 4); a version-2 worker would draw the background.
/// Version 4: settings name a material variant and the light sampler (the light tree), and
/// workers refract through KHR_materials_volume solids and stretch KHR_materials_anisotropy
/// lobes; a version-3 worker would render the same job otherwise.
pub const PROTOCOL_VERSION: u32 = 4;

/// Refuses a peer that speaks another protocol version, naming both.
#[allow(clippy::result_large_err)]
pub fn check_version(theirs: u32) -> Result<(), tonic::Status> {
    if theirs == PROTOCOL_VERSION {
        Ok(())
    } else {
        Err(tonic::Status::failed_precondition(format!(
            "protocol version mismatch: this coordinator speaks version {PROTOCOL_VERSION}, the request came with version {theirs}"
        )))
    }
}

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum WireError {
    #[error("tile sums: {0}")]
    Sums(String),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn other_versions_are_refused_naming_both() {
        assert!(check_version(PROTOCOL_VERSION).is_ok());
        let status = check_version(7).unwrap_err();
        assert_eq!(status.code(), tonic::Code::FailedPrecondition);
        assert!(status.message().contains("version 4") && status.message().contains("version 7"));
    }
}
