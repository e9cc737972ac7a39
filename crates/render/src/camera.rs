//! Pinhole and orthographic cameras in glTF conventions (looking down -z, +y up).

use crate::accel::PACKET;
use crate::math::sqrt4;
use glam::{Mat4, Vec2, Vec3, Vec4};

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Projection {
    /// Vertical field of view in radians.
    Perspective { yfov: f32 },
    /// Half the height of the view volume in world units (glTF `ymag`).
    Orthographic { ymag: f32 },
}

#[derive(Clone, Debug)]
pub struct Camera {
    pub name: String,
    /// Camera-to-world transform; any scale is removed from ray directions.
    pub to_world: Mat4,
    pub projection: Projection,
}

impl Camera {
    /// The ray through film position `film` (in pixels, origin top-left) of a `width` x `height` image.
    pub fn generate_ray(&self, width: u32, height: u32, film: Vec2) -> (Vec3, Vec3) {
        self.film(width, height).ray(film)
    }

    /// The camera's rays for a `width` x `height` image, with what every ray shares (the field of
    /// view's tangent, the aspect ratio) computed once.
    pub fn film(&self, width: u32, height: u32) -> FilmRays<'_> {
        let tan_half_fov = match self.projection {
            Projection::Perspective { yfov } => libm::tanf(0.5 * yfov),
            Projection::Orthographic { .. } => 0.0,
        };
        let (width, height) = (width as f32, height as f32);
        let origin = self.to_world.transform_point3(Vec3::ZERO);
        FilmRays { camera: self, width, height, aspect: width / height, tan_half_fov, origin }
    }

    /// A perspective camera looking at a bounding box from its +z side, the whole box in view.
    pub fn framing(min: Vec3, max: Vec3) -> Self {
        let yfov = 45f32.to_radians();
        let center = 0.5 * (min + max);
        let radius = (0.5 * (max - min).length()).max(1e-6);
        let distance = radius / libm::sinf(0.5 * yfov);
        let eye = center + Vec3::new(0.0, 0.25, 1.0).normalize() * distance;
        Self {
            name: "framing".into(),
            to_world: look_at(eye, center, Vec3::Y),
            projection: Projection::Perspective { yfov },
        }
    }
}

/// A camera's rays through one image's film: [`Camera::film`].
pub struct FilmRays<'a> {
    camera: &'a Camera,
    width: f32,
    height: f32,
    aspect: f32,
    tan_half_fov: f32,
    /// Where a perspective camera's rays start (the same point for all of them).
    origin: Vec3,
}

impl FilmRays<'_> {
    /// The ray through film position `film` (in pixels, origin top-left).
    pub fn ray(&self, film: Vec2) -> (Vec3, Vec3) {
        let aspect = self.aspect;
        let ndc_x = 2.0 * film.x / self.width - 1.0;
        let ndc_y = 1.0 - 2.0 * film.y / self.height;
        let (origin, dir) = match self.camera.projection {
            Projection::Perspective { .. } => {
                let t = self.tan_half_fov;
                (Vec3::ZERO, Vec3::new(ndc_x * t * aspect, ndc_y * t, -1.0))
            }
            Projection::Orthographic { ymag } => (Vec3::new(ndc_x * ymag * aspect, ndc_y * ymag, 0.0), Vec3::NEG_Z),
        };
        let o = self.camera.to_world.transform_point3(origin);
        let d = self.camera.to_world.transform_vector3(dir).normalize();
        (o, d)
    }

    /// [`FilmRays::ray`] through each of `film`, into `rays` as `(o, d, f32::INFINITY)`: the same
    /// rays bit for bit, a packet at a time. A perspective camera's rays are worked out lane by
    /// lane, each lane with exactly the operations of `ray` (glam's order, no fused
    /// multiply-add), so that the compiler can put the lanes in SIMD registers, and their shared
    /// origin is transformed once per film.
    pub fn rays(&self, film: &[Vec2; PACKET], rays: &mut [(Vec3, Vec3, f32); PACKET]) {
        let Projection::Perspective { .. } = self.camera.projection else {
            for (ray, &f) in rays.iter_mut().zip(film) {
                let (o, d) = self.ray(f);
                *ray = (o, d, f32::INFINITY);
            }
            return;
        };
        let (t, aspect) = (self.tan_half_fov, self.aspect);
        let m = &self.camera.to_world;
        let (cx, cy, cz) = (m.x_axis, m.y_axis, m.z_axis);
        let splat = Vec4::splat;
        // Four lanes at a time in SIMD registers (glam's `Vec4` on SSE2), each lane with the
        // operations of `ray`: packed division and square root round each lane exactly as the
        // scalar ones do.
        let mut d = [[0.0f32; PACKET]; 3];
        for half in 0..PACKET / 4 {
            let f = &film[4 * half..4 * half + 4];
            let x = Vec4::new(f[0].x, f[1].x, f[2].x, f[3].x);
            let y = Vec4::new(f[0].y, f[1].y, f[2].y, f[3].y);
            let x = (splat(2.0) * x / splat(self.width) - splat(1.0)) * splat(t) * splat(aspect);
            let y = (splat(1.0) - splat(2.0) * y / splat(self.height)) * splat(t);
            let z = splat(-1.0);
            // Mat4::transform_vector3: x_axis * x, then y_axis * y added, then z_axis * z added.
            let w = [splat(cx.x) * x, splat(cx.y) * x, splat(cx.z) * x];
            let w = [splat(cy.x) * y + w[0], splat(cy.y) * y + w[1], splat(cy.z) * y + w[2]];
            let w = [splat(cz.x) * z + w[0], splat(cz.y) * z + w[1], splat(cz.z) * z + w[2]];
            // Vec3::normalize: times 1 / sqrt(x x + y y + z z).
            let recip = splat(1.0) / Vec4::from_array(sqrt4((w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).to_array()));
            for (axis, w) in d.iter_mut().zip(w) {
                axis[4 * half..4 * half + 4].copy_from_slice(&(w * recip).to_array());
            }
        }
        for (k, ray) in rays.iter_mut().enumerate() {
            *ray = (self.origin, Vec3::new(d[0][k], d[1][k], d[2][k]), f32::INFINITY);
        }
    }
}

/// Camera-to-world transform of a camera at `eye` looking at `target` (glTF: looking down -z).
pub fn look_at(eye: Vec3, target: Vec3, up: Vec3) -> Mat4 {
    let forward = (target - eye).normalize();
    let right = forward.cross(up).normalize();
    let up = right.cross(forward);
    Mat4::from_cols(right.extend(0.0), up.extend(0.0), (-forward).extend(0.0), eye.extend(1.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A packet's rays are the rays `ray` gives one at a time, bit for bit, for a turned and
    /// moved camera of either projection, with film positions all over an odd-sized film.
    #[test]
    fn packet_rays_are_the_single_rays() {
        let to_world = Mat4::from_rotation_translation(
            glam::Quat::from_euler(glam::EulerRot::YXZ, 0.7, -0.3, 0.2),
            Vec3::new(1.5, -2.0, 7.25),
        );
        for projection in [Projection::Perspective { yfov: 0.9 }, Projection::Orthographic { ymag: 2.5 }] {
            let camera = Camera { name: "test".into(), to_world, projection };
            let film_rays = camera.film(317, 191);
            let mut state = 12345u32;
            let mut next = || {
                state = state.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
                (state >> 8) as f32 / (1 << 24) as f32
            };
            for _ in 0..200 {
                let film: [Vec2; PACKET] = std::array::from_fn(|_| Vec2::new(next() * 317.0, next() * 191.0));
                let mut rays = [(Vec3::ZERO, Vec3::ZERO, 0.0); PACKET];
                film_rays.rays(&film, &mut rays);
                for (&f, &(o, d, tmax)) in film.iter().zip(&rays) {
                    let (o1, d1) = film_rays.ray(f);
                    assert_eq!(o.to_array().map(f32::to_bits), o1.to_array().map(f32::to_bits), "{projection:?} {f}");
                    assert_eq!(d.to_array().map(f32::to_bits), d1.to_array().map(f32::to_bits), "{projection:?} {f}");
                    assert_eq!(tmax, f32::INFINITY);
                }
            }
        }
    }
}
