//! The renderable scene: the container of a mesh in BVH order, its materials, lights and
//! cameras, and the ray queries the estimators ask of it (closest hit, occlusion, transmittance
//! through thin walls, emission and BSDF at a surface point). [`SceneBuilder`] is how loaders
//! (glTF, built-ins) make one.

use crate::accel::{Bvh, PACKET, row};
use crate::camera::Camera;
use crate::channels::{Channels, ColorModel};
use crate::envmap::EnvMap;
use crate::interaction::{Hit, SurfacePoint};
use crate::light::{LightSet, PunctualLight};
use crate::material::{Material, Surfaces};
use crate::mesh::{ALPHA_TESTED, HAS_COLORS, Mesh, MeshData, SceneError};
use crate::sampler::{mix64, unit_f32};
use crate::texture::{Image, Texture};
use glam::{Mat4, Vec3, Vec4};
use std::sync::Arc;

pub struct Scene {
    pub mesh: Mesh,
    pub bvh: Bvh,
    pub surfaces: Surfaces,
    pub lights: LightSet,
    pub cameras: Vec<Camera>,
    pub bounds: (Vec3, Vec3),
    /// Ray-origin offset: relative to the scene's size and distance from the origin.
    pub ray_epsilon: f32,
    /// True when any triangle's material cuts out by alpha (mask or blend).
    pub alpha_tested: bool,
    /// True when some triangle's material transmits (KHR_materials_transmission): shadow rays
    /// then look for smooth thin walls to pass ([`Scene::transmittance`]).
    pub thin_walls: bool,
    /// Per material, whether some triangle uses it.
    pub(crate) used: Vec<bool>,
    /// True when some triangle has vertex colours.
    pub(crate) vertex_colors: bool,
}

/// A number in `[0, 1)` that is a pure function of a ray and a triangle, for stochastic alpha
/// blending: rays are continuous random variables, so it is as good as a fresh uniform one
/// (pbrt-v4 hashes the ray the same way), and the triangle makes each layer's number its own.
fn ray_hash(o: Vec3, d: Vec3, triangle: u32) -> f32 {
    let bits = |v: Vec3| ((v.x.to_bits() as u64) << 32 | v.y.to_bits() as u64) ^ (v.z.to_bits() as u64).rotate_left(17);
    let h = mix64(bits(o) ^ mix64(bits(d) ^ mix64(triangle as u64)));
    unit_f32(h)
}

/// Smooth thin walls a shadow ray or a path passes straight through before it gives up: a bound
/// that only degenerate geometry (a stack of coincident panes) reaches.
pub const MAX_WALLS_PASSED: u32 = 16;

/// Collects geometry and materials, then builds the BVH and light distribution.
#[derive(Default)]
pub struct SceneBuilder {
    mesh: Mesh,
    pub materials: Vec<Material>,
    pub images: Vec<Image>,
    pub textures: Vec<Texture>,
    pub punctual: Vec<PunctualLight>,
    pub cameras: Vec<Camera>,
    pub environment: Vec3,
    /// Triangles dropped because they have no area.
    pub degenerate_triangles: usize,
}

impl SceneBuilder {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn add_material(&mut self, m: Material) -> u32 {
        self.materials.push(m);
        (self.materials.len() - 1) as u32
    }

    pub fn triangle_count(&self) -> usize {
        self.mesh.triangles.len()
    }

    /// Adds a mesh primitive placed by `transform` (object to world).
    pub fn add_mesh(&mut self, name: &str, mesh: MeshData, transform: Mat4) -> Result<(), SceneError> {
        self.degenerate_triangles += self.mesh.add(name, mesh, transform, &self.materials)?;
        Ok(())
    }

    /// Builds the BVH (reordering triangles to BVH order) and the light distribution.
    pub fn build(self) -> Scene {
        let corners: Vec<[Vec3; 3]> = self.mesh.triangles.iter().map(|t| self.mesh.corners(t)).collect();
        // The BSDFs' tables are made while the tree is built (on another thread where the pool
        // has one), not in the first samples, where every render thread would wait for them.
        let sheen = self.materials.iter().any(|m| m.sheen_color != Vec3::ZERO);
        let ((bvh, order), ()) = rayon::join(
            || Bvh::build(&corners),
            || {
                crate::bsdf::energy::prepare();
                if sheen {
                    crate::bsdf::sheen::prepare();
                }
            },
        );
        let mesh = self.mesh.reordered(&order);
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for t in &mesh.triangles {
            for p in mesh.corners(t) {
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        for l in &self.punctual {
            if let Some(p) = l.position() {
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        if lo.x > hi.x {
            (lo, hi) = (Vec3::splat(-1.0), Vec3::splat(1.0));
        }
        let extent = (hi - lo).max_element().max(1e-6);
        let magnitude = lo.abs().max(hi.abs()).max_element();
        let ray_epsilon = 1e-5 * extent.max(magnitude);
        let mut scene = Scene {
            mesh,
            bvh,
            surfaces: Surfaces::new(self.materials, self.images, self.textures),
            lights: LightSet::default(),
            cameras: self.cameras,
            bounds: (lo, hi),
            ray_epsilon,
            alpha_tested: false,
            thin_walls: false,
            used: Vec::new(),
            vertex_colors: false,
        };
        scene.alpha_tested = scene.mesh.triangles.iter().any(|t| t.flags & ALPHA_TESTED != 0);
        scene.vertex_colors = scene.mesh.triangles.iter().any(|t| t.flags & HAS_COLORS != 0);
        scene.used = vec![false; scene.surfaces.materials().len()];
        for t in &scene.mesh.triangles {
            if let Some(used) = scene.used.get_mut(t.material as usize) {
                *used = true;
            }
        }
        let thin_walls = scene.used_materials().any(|m| m.transmission > 0.0);
        scene.thin_walls = thin_walls;
        scene.lights = scene.light_set(self.punctual, self.environment, None);
        scene
    }
}

impl Scene {
    pub fn diagonal(&self) -> f32 {
        (self.bounds.1 - self.bounds.0).length()
    }

    /// The lights of this scene's emissive triangles with `punctual` lights and an environment
    /// (see [`LightSet::build`]).
    pub fn light_set(&self, punctual: Vec<PunctualLight>, environment: Vec3, map: Option<Arc<EnvMap>>) -> LightSet {
        LightSet::build(&self.mesh, &self.surfaces, self.diagonal(), punctual, environment, map)
    }

    /// False when the hit point lies in a cut-out (alpha mask) part of the triangle, or when the
    /// ray passes a blended one (see [`Material::is_cut_out`]).
    fn accepts(&self, slot: u32, o: Vec3, d: Vec3, t: f32) -> bool {
        let tri = &self.mesh.triangles[slot as usize];
        if tri.flags & ALPHA_TESTED == 0 {
            return true;
        }
        let b = self.mesh.barycentrics(tri, o + d * t);
        let ctx = self.mesh.texture_context(&self.surfaces, tri, b);
        !self.surfaces.materials()[tri.material as usize].is_cut_out(&ctx, || ray_hash(o, d, slot))
    }

    pub fn intersect(&self, o: Vec3, d: Vec3, tmax: f32) -> Option<Hit> {
        let hit = if self.alpha_tested {
            self.bvh.closest_hit(o, d, tmax, |slot, t| self.accepts(slot, o, d, t))
        } else {
            self.bvh.closest_hit(o, d, tmax, |_, _| true) // no cut-outs: skip the per-hit lookup
        };
        hit.map(|(triangle, t)| Hit { triangle, t })
    }

    /// [`Scene::intersect`] for up to [`PACKET`] rays `(o, d, tmax)` at once, with the same answers;
    /// faster when the rays are coherent (camera rays of one pixel or of neighbours).
    pub fn intersect_packet(&self, rays: &[(Vec3, Vec3, f32)]) -> [Option<Hit>; PACKET] {
        let hits = if self.alpha_tested {
            self.bvh.closest_hits(rays, |r, slot, t| self.accepts(slot, rays[r].0, rays[r].1, t))
        } else {
            self.bvh.closest_hits(rays, |_, _, _| true)
        };
        hits.map(|h| h.map(|(triangle, t)| Hit { triangle, t }))
    }

    /// [`Scene::intersect`] for each of `rays` `(o, d, tmax)`, into `out`, with the same answers;
    /// faster than one by one when the rays are incoherent and the scene big (see
    /// `Bvh::closest_hits_stream`).
    pub fn intersect_stream(&self, rays: &[(Vec3, Vec3, f32)], out: &mut [Option<Hit>]) {
        assert_eq!(rays.len(), out.len(), "one answer per ray");
        let found = |r: usize, hit: Option<(u32, f32)>| out[r] = hit.map(|(triangle, t)| Hit { triangle, t });
        if self.alpha_tested {
            self.bvh.closest_hits_stream(rays, |r, slot, t| self.accepts(slot, rays[r].0, rays[r].1, t), found)
        } else {
            self.bvh.closest_hits_stream(rays, |_, _, _| true, found)
        }
    }

    /// [`Scene::intersect`] for the rays of the lanes where `live`, as rows of eight
    /// (`o[axis][lane]`), each `tmax` infinite; each lane's answer is its own call's.
    pub(crate) fn intersect8(&self, o: &[[f32; 8]; 3], d: &[[f32; 8]; 3], live: [bool; 8]) -> [Option<Hit>; 8] {
        if self.alpha_tested {
            return std::array::from_fn(|i| live[i].then(|| self.intersect(row(o, i), row(d, i), f32::INFINITY))?);
        }
        let hits = self.bvh.closest_hits8(o, d, &[f32::INFINITY; 8], live);
        hits.map(|h| h.map(|(triangle, t)| Hit { triangle, t }))
    }

    pub fn occluded(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        if self.alpha_tested {
            self.bvh.occluded(o, d, tmax, |slot, t| self.accepts(slot, o, d, t))
        } else {
            self.bvh.occluded(o, d, tmax, |_, _| true)
        }
    }

    /// [`Scene::occluded`], inlined where the caller is (the wave's shadow rays).
    #[inline(always)]
    pub(crate) fn occluded_inline(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        match self.alpha_tested {
            true => self.occluded(o, d, tmax),
            false => self.bvh.occluded_plain(o, d, tmax),
        }
    }

    /// A ray origin just off the surface, on the side `w` points to.
    pub fn offset_origin(&self, sp: &SurfacePoint, w: Vec3) -> Vec3 {
        sp.offset_origin(w, self.ray_epsilon)
    }

    /// The surface point of a hit, for a ray from `o` with direction `d`.
    pub fn surface(&self, hit: Hit, o: Vec3, d: Vec3) -> SurfacePoint {
        SurfacePoint::at(&self.mesh, &self.surfaces, hit, o, d)
    }

    /// Is `to` visible from surface point `sp`? (The shadow ray stops short of `to` by epsilon.)
    pub fn visible(&self, sp: &SurfacePoint, wi: Vec3, distance: f32) -> bool {
        let o = self.offset_origin(sp, wi);
        let tmax = distance - 2.0 * self.ray_epsilon;
        tmax <= 0.0 || !self.occluded(o, wi, tmax)
    }

    /// What reaches surface point `sp` from `distance` along `wi`: `None` when something opaque
    /// is in the way, else the product of [`Bsdf::straight_through`] over the smooth thin walls
    /// the shadow ray passes (one when there are none). Light sampling through a glass pane is
    /// what lets a point light or the sun shine through it: no BSDF-sampled path can hit them.
    ///
    /// [`Bsdf::straight_through`]: crate::bsdf::Bsdf::straight_through
    pub fn transmittance<M: ColorModel>(&self, sp: &SurfacePoint, wi: Vec3, distance: f32, model: &M) -> Option<M::C> {
        if !self.thin_walls {
            return self.visible(sp, wi, distance).then_some(M::C::ONE);
        }
        let target = sp.p + wi * distance;
        let mut o = self.offset_origin(sp, wi);
        let mut through = M::C::ONE;
        for _ in 0..=MAX_WALLS_PASSED {
            let tmax = if distance.is_finite() { o.distance(target) - 2.0 * self.ray_epsilon } else { f32::INFINITY };
            let Some(hit) = (tmax > 0.0).then(|| self.intersect(o, wi, tmax)).flatten() else {
                return Some(through);
            };
            let wall = self.surface(hit, o, wi);
            if !self.may_pass(&wall) {
                return None;
            }
            // A thin wall's straight-through weight has no rough lobe to compensate.
            let t = self.bsdf_compensated(&wall, model).straight_through(wall.frame.to_local(-wi));
            if t.max_element() <= 0.0 {
                return None;
            }
            through *= t;
            o = self.offset_origin(&wall, wi);
        }
        None
    }

    /// True when `sp`'s material transmits, so that it may be a smooth thin wall that light passes
    /// straight through (its BSDF decides: [`crate::bsdf::Bsdf::straight_through`]).
    pub fn may_pass(&self, sp: &SurfacePoint) -> bool {
        self.thin_walls && self.surfaces.materials()[sp.material as usize].transmission > 0.0
    }

    /// What the medium of a refracting solid absorbed over the `t` a ray travelled to reach `sp`,
    /// when it reached it from inside (its back face); `None` where nothing was absorbed.
    /// Solids are taken to be closed and apart: a ray inside one meets its boundary next.
    pub fn absorption<M: ColorModel>(&self, sp: &SurfacePoint, t: f32, model: &M) -> Option<M::C> {
        let material = &self.surfaces.materials()[sp.material as usize];
        if sp.front_face || !material.refracts() {
            return None;
        }
        material.absorption(t, model)
    }

    /// Emitted radiance leaving `sp` towards the viewer.
    pub fn emission<M: ColorModel>(&self, sp: &SurfacePoint, model: &M) -> M::C {
        let material = &self.surfaces.materials()[sp.material as usize];
        if !material.is_emissive() || !(sp.front_face || material.double_sided) {
            return M::C::ZERO;
        }
        self.surfaces.emission_at(sp.material, || sp.uv, sp.color, model)
    }

    /// The BSDF at `sp`; `compensated`: glTF materials with energy compensation
    /// ([`crate::settings::RenderSettings::energy_compensation`]).
    pub fn bsdf<M: ColorModel>(&self, sp: &SurfacePoint, model: &M, compensated: bool) -> crate::bsdf::Bsdf<M::C> {
        let bsdf = self.bsdf_compensated(sp, model);
        if compensated { bsdf } else { bsdf.without_compensation() }
    }

    fn bsdf_compensated<M: ColorModel>(&self, sp: &SurfacePoint, model: &M) -> crate::bsdf::Bsdf<M::C> {
        // Without refraction, an anisotropy direction or a coat normal nothing below changes it.
        if sp.color == Vec4::ONE
            && sp.anisotropy.is_none()
            && sp.coat_normal.is_none()
            && let Some(bsdf) = self.surfaces.constant_bsdf::<M::C>(sp.material)
        {
            return bsdf;
        }
        let ctx = self.surfaces.context(sp.uv, sp.color);
        let material = &self.surfaces.materials()[sp.material as usize];
        let bsdf = material.bsdf(&ctx, model);
        // A solid met from inside (its back face): the indices trade places.
        let bsdf = if material.refracts() && !sp.front_face { bsdf.from_inside() } else { bsdf };
        let bsdf = match sp.anisotropy {
            Some(direction) => bsdf.with_anisotropy_direction(sp.frame.to_local(direction)),
            None => bsdf,
        };
        match sp.coat_normal {
            Some(n) => bsdf.with_coat_normal(sp.frame.to_local(n)),
            None => bsdf,
        }
    }

    /// The materials (by name) that carry spectral content, with what it is: what makes
    /// `--color auto` render spectrally. Only materials some triangle uses count.
    pub fn spectral_content(&self) -> Vec<String> {
        self.used_materials()
            .filter(|m| m.spectra.is_spectral())
            .map(|m| format!("'{}' ({})", m.name, m.spectra.describe().join(", ")))
            .collect()
    }

    /// The largest directional albedo of any material: `q` of Dimov, Gurov and Penzov.
    pub fn max_albedo(&self) -> f32 {
        self.used_materials().map(|m| m.max_albedo(&self.surfaces.images, &self.surfaces.textures)).fold(0.0, f32::max)
    }

    /// The materials some triangle uses, each once, in index order.
    fn used_materials(&self) -> impl Iterator<Item = &Material> {
        let materials = self.surfaces.materials();
        self.used.iter().zip(materials).filter(|(used, _)| **used).map(|(_, m)| m)
    }
}
