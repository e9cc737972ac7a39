//! The `tessera` object in a material's `extras`, which selects paper 1's physical
//! Cook-Torrance model:
//!
//! ```json
//! "extras": { "tessera": { "model": "cook-torrance", "distribution": "beckmann",
//!                          "n": [0.18, 0.42, 1.37], "k": [3.42, 2.35, 1.77] } }
//! ```
//!
//! `n` and `k` are a number or an RGB triple; `k` absent or 0 means a dielectric (Lambert base
//! under an exact-Fresnel specular layer), `k > 0` a conductor. `distribution` is `ggx`
//! (default) or `beckmann`. Roughness comes from the glTF material as usual.

use serde_json::Value;
use tessera_render::Model;
use tessera_render::bsdf::Distribution;
use tessera_render::glam::Vec3;

/// Parses a material's extras; `Ok(None)` when there is no `tessera` object.
pub fn parse_model(extras: Option<&str>) -> Result<Option<Model>, String> {
    let Some(text) = extras else { return Ok(None) };
    let value: Value = serde_json::from_str(text).map_err(|e| format!("extras are not valid JSON: {e}"))?;
    let Some(t) = value.get("tessera") else {
        return Ok(None);
    };
    let model = t.get("model").and_then(Value::as_str).unwrap_or("cook-torrance");
    if model != "cook-torrance" && model != "gltf" {
        return Err(format!("extras.tessera.model '{model}' is not 'cook-torrance' or 'gltf'"));
    }
    if model == "gltf" {
        return Ok(Some(Model::Gltf));
    }
    let distribution = match t.get("distribution").and_then(Value::as_str).unwrap_or("ggx") {
        "ggx" => Distribution::Ggx,
        "beckmann" => Distribution::Beckmann,
        other => {
            return Err(format!("extras.tessera.distribution '{other}' is not 'ggx' or 'beckmann'"));
        }
    };
    let n = rgb(t.get("n"), "n")?.unwrap_or(Vec3::splat(1.5));
    let k = rgb(t.get("k"), "k")?.unwrap_or(Vec3::ZERO);
    if n.min_element() <= 0.0 || k.min_element() < 0.0 {
        return Err(format!("extras.tessera: need n > 0 and k >= 0 (got n={n}, k={k})"));
    }
    Ok(Some(Model::CookTorrance { distribution, n, k }))
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
        let m = parse_model(Some(r#"{"tessera":{"distribution":"beckmann","n":[0.2,0.4,1.4],"k":3}}"#)).unwrap();
        assert_eq!(
            m,
            Some(Model::CookTorrance {
                distribution: Distribution::Beckmann,
                n: Vec3::new(0.2, 0.4, 1.4),
                k: Vec3::splat(3.0)
            })
        );
    }

    #[test]
    fn other_extras_are_ignored_and_bad_values_named() {
        assert_eq!(parse_model(Some(r#"{"author":"x"}"#)).unwrap(), None);
        let err = parse_model(Some(r#"{"tessera":{"distribution":"phong"}}"#)).unwrap_err();
        assert!(err.contains("phong"), "{err}");
        let err = parse_model(Some(r#"{"tessera":{"n":[1,2]}}"#)).unwrap_err();
        assert!(err.contains("tessera.n"), "{err}");
    }
}
