//! The `tessera` header attribute, written the same way by every path that makes an image.

/// `key=value` lines recording what made an image.
pub fn image_metadata(
    scene: &str,
    scene_hash: &str,
    seed: u64,
    spp: u32,
    environment: [f32; 3],
    settings: &str,
    dropped: u64,
) -> String {
    format!(
        "scene={scene}\nscene_hash={scene_hash}\nseed={seed}\nspp={spp}\nenvironment=[{}, {}, {}]\nsettings={settings}\ndropped_samples={dropped}\nsoftware=tessera {}\n",
        environment[0],
        environment[1],
        environment[2],
        env!("CARGO_PKG_VERSION"),
    )
}
