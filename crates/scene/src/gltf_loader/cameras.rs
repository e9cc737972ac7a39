//! Cameras and KHR_lights_punctual lights at their nodes' world transforms.

use gltf::khr_lights_punctual::Kind;
use tessera_render::glam::{Mat4, Vec3};
use tessera_render::{Camera, Projection, PunctualLight};

pub(super) fn convert_camera(camera: &gltf::Camera, world: Mat4, index: usize) -> Result<Camera, String> {
    let name = camera.name().map_or_else(|| format!("camera{index}"), str::to_string);
    let projection = match camera.projection() {
        gltf::camera::Projection::Perspective(p) => {
            let yfov = p.yfov();
            if !(yfov > 0.0 && yfov < std::f32::consts::PI) {
                return Err(format!("camera '{name}': yfov {yfov} is not between 0 and pi"));
            }
            Projection::Perspective { yfov }
        }
        gltf::camera::Projection::Orthographic(o) => {
            let ymag = o.ymag().abs();
            if !(ymag > 0.0 && ymag.is_finite()) {
                return Err(format!("camera '{name}': ymag {} must be positive and finite", o.ymag()));
            }
            Projection::Orthographic { ymag }
        }
    };
    if !world.is_finite() || world.determinant() == 0.0 {
        return Err(format!("camera '{name}': its node transform is singular or not finite"));
    }
    Ok(Camera { name, to_world: world, projection })
}

pub(super) fn describe_camera(c: &Camera) -> String {
    match c.projection {
        Projection::Perspective { yfov } => format!("'{}' perspective, yfov {:.1} deg", c.name, yfov.to_degrees()),
        Projection::Orthographic { ymag } => format!("'{}' orthographic, ymag {ymag}", c.name),
    }
}

/// The light in world space; `None` when anything about it is not finite.
pub(super) fn convert_light(light: &gltf::khr_lights_punctual::Light, world: Mat4) -> Option<PunctualLight> {
    let color = Vec3::from_array(light.color()) * light.intensity().max(0.0);
    let position = world.transform_point3(Vec3::ZERO);
    let direction = world.transform_vector3(Vec3::NEG_Z).normalize_or(Vec3::NEG_Z);
    if !(color.is_finite() && position.is_finite() && direction.is_finite()) {
        return None;
    }
    Some(match light.kind() {
        Kind::Directional => PunctualLight::Directional { direction, illuminance: color },
        Kind::Point => PunctualLight::Point { position, intensity: color, range: light.range() },
        Kind::Spot { inner_cone_angle, outer_cone_angle } => PunctualLight::Spot {
            position,
            direction,
            intensity: color,
            cos_inner: libm::cosf(inner_cone_angle),
            cos_outer: libm::cosf(outer_cone_angle),
            range: light.range(),
        },
    })
}
