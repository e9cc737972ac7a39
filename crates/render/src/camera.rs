//! Pinhole and orthographic cameras in glTF conventions (looking down -z, +y up).

use glam::{Mat4, Vec2, Vec3};

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
        FilmRays { camera: self, width, height, aspect: width / height, tan_half_fov }
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
}

/// Camera-to-world transform of a camera at `eye` looking at `target` (glTF: looking down -z).
pub fn look_at(eye: Vec3, target: Vec3, up: Vec3) -> Mat4 {
    let forward = (target - eye).normalize();
    let right = forward.cross(up).normalize();
    let up = right.cross(forward);
    Mat4::from_cols(right.extend(0.0), up.extend(0.0), (-forward).extend(0.0), eye.extend(1.0))
}
