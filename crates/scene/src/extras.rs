//! The `tessera` object in a material's `extras`: Dimov, Gurov and Penzov's physical Cook-Torrance model, named
//! metals and measured spectra.
//!
//! ```json
//! "extras": { "tessera": { "model": "cook-torrance", "distribution": "beckmann",
//!                          "n": [0.18, 0.42, 1.37], "k": [3.42, 2.35, 1.77] } }
//! "extras": { "tessera": { "conductor": "Au" } }
//! "extras": { "tessera": { "reflectance": { "wavelengths": [400, 500, 600, 700],
//!                                           "values": [0.05, 0.3, 0.6, 0.7] } } }
//! "extras": { "tessera": { "emission": { "wavelengths": [400, 700], "values": [0.5, 1.0] } } }
//! ```
//!
//! `n` and `k` are a number or an RGB triple; `k` absent or 0 means a dielectric (Lambert base
//! under an exact-Fresnel specular layer), `k > 0` a conductor. `conductor` names a metal with
//! measured `n(lambda)`, `k(lambda)` (Au, Ag, Cu, Al) instead. `distribution` is `ggx` (default)
//! or `beckmann`; roughness comes from the glTF material as usual. `reflectance` replaces
//! `baseColorFactor`; `emission` gives the emitter's spectral shape, whose luminance is the
//! emissive colour's. Tables are linear between points and constant beyond them.

use serde_json::Value;
use std::sync::Arc;
use tessera_render::Model;
use tessera_render::bsdf::Distribution;
use tessera_render::glam::Vec3;
use tessera_render::spectral::{RGB_WAVELENGTHS, Spectrum, data};
use tessera_render::{EmissionSpectrum, MaterialSpectra};

/// What a material's `extras.tessera` says.
#[derive(Clone, Debug, Default)]
pub struct Extras {
    /// The reflection model, when the extras choose one.
    pub model: Option<Model>,
    pub spectra: MaterialSpectra,
}

/// Parses a material's extras; the default (nothing chosen) when there is no `tessera` object.
pub fn parse(extras: Option<&str>) -> Result<Extras, String> {
    let Some(text) = extras else { return Ok(Extras::default()) };
    let value: Value = serde_json::from_str(text).map_err(|e| format!("extras are not valid JSON: {e}"))?;
    let Some(t) = value.get("tessera") else {
        return Ok(Extras::default());
    };
    let mut spectra = MaterialSpectra {
        reflectance: table(t.get("reflectance"), "reflectance", 0.0..=1.0)?.map(Arc::new),
        emission: None,
        conductor: None,
    };
    if let Some(shape) = table(t.get("emission"), "emission", 0.0..=f64::MAX)? {
        let shape = EmissionSpectrum::new(Arc::new(shape))
            .ok_or("extras.tessera.emission has no luminance (it is zero over 380-780 nm)")?;
        spectra.emission = Some(shape);
    }
    let model = t.get("model").and_then(Value::as_str);
    if let Some(m) = model.filter(|m| *m != "cook-torrance" && *m != "gltf") {
        return Err(format!("extras.tessera.model '{m}' is not 'cook-torrance' or 'gltf'"));
    }
    let conductor = t.get("conductor");
    // Without a model, the object means Cook-Torrance unless it only carries spectra.
    let has = |key: &str| t.get(key).is_some();
    let wants_cook_torrance = match model {
        Some(m) => m == "cook-torrance",
        None => {
            ["conductor", "n", "k", "distribution"].iter().any(|k| has(k)) || !(has("reflectance") || has("emission"))
        }
    };
    if !wants_cook_torrance {
        if conductor.is_some() {
            return Err("extras.tessera.conductor needs the cook-torrance model".into());
        }
        return Ok(Extras { model: model.map(|_| Model::Gltf), spectra });
    }
    let distribution = match t.get("distribution").and_then(Value::as_str).unwrap_or("ggx") {
        "ggx" => Distribution::Ggx,
        "beckmann" => Distribution::Beckmann,
        other => return Err(format!("extras.tessera.distribution '{other}' is not 'ggx' or 'beckmann'")),
    };
    let (n, k) = match conductor {
        Some(c) => {
            if t.get("n").is_some() || t.get("k").is_some() {
                return Err("extras.tessera: give either conductor or n and k, not both".into());
            }
            let name = c.as_str().ok_or("extras.tessera.conductor must be a string")?;
            let (metal, n, k) = named_metal(name).map_err(|e| format!("extras.tessera.conductor {e}"))?;
            spectra.conductor = Some(metal);
            (n, k)
        }
        None => (rgb(t.get("n"), "n")?.unwrap_or(Vec3::splat(1.5)), rgb(t.get("k"), "k")?.unwrap_or(Vec3::ZERO)),
    };
    if n.min_element() <= 0.0 || k.min_element() < 0.0 {
        return Err(format!("extras.tessera: need n > 0 and k >= 0 (got n={n}, k={k})"));
    }
    Ok(Extras { model: Some(Model::CookTorrance { distribution, n, k }), spectra })
}

/// A metal of [`data::METALS`] by name (any case): its canonical name, and the `n`, `k` that RGB
/// renders use (the measured constants at the RGB wavelengths).
pub fn named_metal(name: &str) -> Result<(&'static str, Vec3, Vec3), String> {
    let metal = data::METALS.iter().find(|m| m.eq_ignore_ascii_case(name));
    match (metal, data::metal(name)) {
        (Some(m), Some((n, k))) => {
            let at = |s: &Spectrum| Vec3::from_array(RGB_WAVELENGTHS.map(|l| s.eval(l) as f32));
            Ok((m, at(n), at(k)))
        }
        _ => Err(format!("'{name}' is not a known metal ({})", data::METALS.join(", "))),
    }
}

/// A spectral table `{ "wavelengths": [...nm], "values": [...] }`, wavelengths ascending inside
/// 200..=2000 nm, values finite and inside `range`.
fn table(v: Option<&Value>, name: &str, range: std::ops::RangeInclusive<f64>) -> Result<Option<Spectrum>, String> {
    let Some(v) = v else { return Ok(None) };
    let numbers = |key: &str| -> Result<Vec<f64>, String> {
        let bad = || format!("extras.tessera.{name}.{key} must be an array of numbers");
        v.get(key).and_then(Value::as_array).ok_or_else(bad)?.iter().map(|x| x.as_f64().ok_or_else(bad)).collect()
    };
    let (wavelengths, values) = (numbers("wavelengths")?, numbers("values")?);
    if wavelengths.len() != values.len() || wavelengths.len() < 2 {
        return Err(format!(
            "extras.tessera.{name}: need at least two wavelengths and one value for each (got {} and {})",
            wavelengths.len(),
            values.len()
        ));
    }
    if wavelengths.windows(2).any(|w| w[0] >= w[1]) || wavelengths.iter().any(|l| !(200.0..=2000.0).contains(l)) {
        return Err(format!("extras.tessera.{name}.wavelengths must ascend, in nm, inside 200..=2000"));
    }
    if let Some(x) = values.iter().find(|x| !x.is_finite() || !range.contains(x)) {
        return Err(format!(
            "extras.tessera.{name}: value {x} is outside {}..={}",
            range.start(),
            if *range.end() == f64::MAX { "inf".to_string() } else { range.end().to_string() }
        ));
    }
    Ok(Some(Spectrum::new(wavelengths.into_iter().zip(values).collect())))
}

fn rgb(v: Option<&Value>, name: &str) -> Result<Option<Vec3>, String> {
    let bad = || format!("extras.tessera.{name} must be a number or an array of three numbers");
    match v {
        None => Ok(None),
        Some(Value::Number(x)) => Ok(Some(Vec3::splat(x.as_f64().ok_or_else(bad)? as f32))),
        Some(Value::Array(a)) if a.len() == 3 => {
            let c: Option<Vec<f32>> = a.iter().map(|x| x.as_f64().map(|x| x as f32)).collect();
            let c = c.ok_or_else(bad)?;
            Ok(Some(Vec3::new(c[0], c[1], c[2])))
        }
        Some(_) => Err(bad()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_a_conductor() {
        let m = parse(Some(r#"{"tessera":{"distribution":"beckmann","n":[0.2,0.4,1.4],"k":3}}"#)).unwrap();
        assert_eq!(
            m.model,
            Some(Model::CookTorrance {
                distribution: Distribution::Beckmann,
                n: Vec3::new(0.2, 0.4, 1.4),
                k: Vec3::splat(3.0)
            })
        );
        assert!(!m.spectra.is_spectral());
    }

    #[test]
    fn a_named_metal_is_spectral_content_with_rgb_constants_from_its_table() {
        let m = parse(Some(r#"{"tessera":{"conductor":"au"}}"#)).unwrap();
        assert_eq!(m.spectra.conductor, Some("Au"));
        let Some(Model::CookTorrance { n, k, distribution }) = m.model else { panic!("{:?}", m.model) };
        assert_eq!(distribution, Distribution::Ggx);
        // Gold: n small in the red, larger in the blue; k large in the red.
        assert!(n.x < 0.3 && n.z > 1.0 && k.x > 3.0, "n={n} k={k}");
        let err = parse(Some(r#"{"tessera":{"conductor":"Fe"}}"#)).unwrap_err();
        assert!(err.contains("Fe") && err.contains("Au, Ag, Cu, Al"), "{err}");
        let err = parse(Some(r#"{"tessera":{"conductor":"Au","k":3}}"#)).unwrap_err();
        assert!(err.contains("either"), "{err}");
    }

    #[test]
    fn spectral_tables_are_validated() {
        let ok = r#"{"tessera":{"reflectance":{"wavelengths":[400,700],"values":[0.2,0.8]}}}"#;
        let m = parse(Some(ok)).unwrap();
        assert_eq!(m.model, None);
        assert_eq!(m.spectra.reflectance.as_ref().map(|r| r.eval(550.0)), Some(0.5));
        for (bad, says) in [
            (r#"{"tessera":{"reflectance":{"wavelengths":[400,700],"values":[0.2,1.8]}}}"#, "1.8 is outside"),
            (r#"{"tessera":{"reflectance":{"wavelengths":[700,400],"values":[0.2,0.8]}}}"#, "ascend"),
            (r#"{"tessera":{"reflectance":{"wavelengths":[400],"values":[0.2]}}}"#, "at least two"),
            (r#"{"tessera":{"reflectance":{"wavelengths":[400,500],"values":"x"}}}"#, "array of numbers"),
            (r#"{"tessera":{"emission":{"wavelengths":[400,700],"values":[0,0]}}}"#, "no luminance"),
            (r#"{"tessera":{"emission":{"wavelengths":[400,700],"values":[-1,2]}}}"#, "outside"),
        ] {
            let err = parse(Some(bad)).unwrap_err();
            assert!(err.contains(says), "{bad}: {err}");
        }
    }

    #[test]
    fn other_extras_are_ignored_and_bad_values_named() {
        assert!(parse(Some(r#"{"author":"x"}"#)).unwrap().model.is_none());
        let err = parse(Some(r#"{"tessera":{"distribution":"phong"}}"#)).unwrap_err();
        assert!(err.contains("phong"), "{err}");
        let err = parse(Some(r#"{"tessera":{"n":[1,2]}}"#)).unwrap_err();
        assert!(err.contains("tessera.n"), "{err}");
    }
}
