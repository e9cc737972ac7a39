//! The wave: eight paths side by side for plain scenes: RGB light transport with next-event estimation
//! (and MIS), every material a Lambert surface the same all over. Each lane holds one path; a
//! lane whose path ends takes the tile's next sample at once, so the eight stay full until the
//! tile runs out. The path state lies in structure-of-arrays form (one row of eight per number),
//! and the stages that are arithmetic on it (the surface point, its frame, a point on an
//! emissive triangle, the Lambert lobe, the weights, the next ray) run as branch-free loops over
//! the eight lanes that the compiler puts in SIMD registers (AVX2 where the CPU has it, chosen
//! at run time; SSE otherwise).
//!
//! Each lane makes exactly the IEEE operations the one-path estimator
//! ([`crate::estimator::nee::trace`]) makes, in its order: the same bits for every sample. The
//! eight closest-hit rays of a step (camera rays among them) go to the scene together
//! ([`Scene::intersect8`]), which tests a small scene's triangles against all eight at once and
//! walks a big one's tree ray by ray; shadow rays go one by one. A bounce's numbers come from the
//! sampler eight at a time ([`sampler::bounce_lanes`]), and so do the sines and cosines that turn a
//! direction ([`crate::math::sincos_lanes`], libm's steps in lanes), and with at most eight lights
//! chosen by power, the choice of a light ([`crate::light::LightSet::choose_lanes`]). Elsewhere the
//! choice, and a point on any light but a triangle, are the scalar code's own calls, lane by lane.
//! Samples end in a different order than the pixel loop's, which the sums do not see: they add
//! whole numbers (see [`crate::sums`]).

//!
//! By stage, as pbrt-v4's wavefront integrator: `intersect.rs` (the eight rays traced together,
//! escapes, and the surface points), `emission.rs` (what the hit emits), `light.rs` (the light
//! sample), `scatter.rs` (the Lambert lobe's light weights and shadow rays, its sampled direction,
//! the path's weight and next ray, roulette); `paths.rs` holds the lanes' state.

// A lane's loop reads and writes several rows at its index.
#![allow(clippy::needless_range_loop)]

mod emission;
mod intersect;
mod light;
mod paths;
mod scatter;

use crate::bsdf::Bsdf;
use crate::camera::Camera;
use crate::estimator::nee::Combination;
use crate::lanes::{Lanes, dispatch};
use crate::sampler;
use crate::scene::Scene;
use crate::settings::{ColorMode, Estimator, RenderSettings};
use crate::sums::{Tile, TileSums};
use glam::Vec3;
use intersect::Points;
use paths::{Paths, Queue, Rows};
use std::ops::Range;

/// Paths side by side.
const W: usize = sampler::LANES;

type Row = [f32; W];

/// What the wave needs of a material: its BSDF (a Lambert lobe) and, where it glows, what it
/// emits and whether from both faces.
#[derive(Clone, Copy)]
struct Plain {
    bsdf: Bsdf<Vec3>,
    /// [`Bsdf::has_smooth_part`]: whether light sampling can reach it.
    smooth: bool,
    emission: Option<Vec3>,
    double_sided: bool,
}

/// A scene and settings the wave renders: see [`Wave::for_render`].
pub(crate) struct Wave {
    /// Per material, what the wave needs of it where it is plain.
    materials: Vec<Option<Plain>>,
    combination: Combination,
}

impl Wave {
    /// The wave for `scene` under `settings` where it renders them: RGB, next-event estimation
    /// or MIS, no thin walls, no vertex colours, and every material a plain Lambert surface
    /// (the same BSDF and emission at every point: no texture, normal map, clear coat,
    /// anisotropy or refraction). `None` elsewhere: the one-path estimators render those.
    pub(crate) fn for_render(scene: &Scene, settings: &RenderSettings) -> Option<Wave> {
        let combination = match settings.estimator {
            Estimator::Mis => Combination::PowerHeuristic,
            Estimator::Nee => Combination::LightOnly,
            Estimator::Collision => return None,
        };
        if settings.color != ColorMode::Rgb || scene.thin_walls {
            return None;
        }
        if scene.vertex_colors {
            return None;
        }
        let surfaces = &scene.surfaces;
        let plain = |k: usize| {
            let m = &surfaces.materials()[k];
            let bsdf = surfaces.constant_rgb_bsdf(k as u32).filter(|b| b.is_lambert() && !b.transmits())?;
            let plain = m.normal_texture.is_none() && m.clearcoat <= 0.0 && !m.is_anisotropic() && !m.refracts();
            let emission = match m.is_emissive() {
                true => Some(surfaces.constant_rgb_emission(k as u32)?),
                false => None,
            };
            plain.then_some(Plain { bsdf, smooth: bsdf.has_smooth_part(), emission, double_sided: m.double_sided })
        };
        // Every material a triangle uses must be plain; the others do not matter. (Asked for each
        // tile, so from what the scene worked out once, not from its triangles.)
        let used = |k: usize| scene.used.get(k).copied().unwrap_or(false);
        let materials: Vec<Option<Plain>> = (0..surfaces.materials().len()).map(plain).collect();
        if materials.iter().enumerate().any(|(k, m)| used(k) && m.is_none()) {
            return None;
        }
        Some(Wave { materials, combination })
    }

    /// Samples `samples` of every pixel of `tile`: the sums [`crate::tile::render_tile`] gives.
    pub(crate) fn render(
        &self,
        scene: &Scene,
        settings: &RenderSettings,
        camera: &Camera,
        tile: Tile,
        samples: Range<u32>,
    ) -> TileSums {
        self.render_with(Lanes::widest(), scene, settings, camera, tile, samples)
    }

    /// [`Wave::render`] with the lane loops compiled for `lanes`, which must run on this CPU. All
    /// give the same bits: the instructions differ (AVX-512 has masked stores and 32 registers,
    /// where AVX2 spills and uses `VMASKMOVPS`; Cornell 256 x 256, 32 spp, one thread, on this
    /// project's Zen 4: medians 1.80 s against 1.68 s and 1.74 s against 1.50 s in two sets of six
    /// alternating runs), the operations do not.
    pub(crate) fn render_with(
        &self,
        lanes: Lanes,
        scene: &Scene,
        settings: &RenderSettings,
        camera: &Camera,
        tile: Tile,
        samples: Range<u32>,
    ) -> TileSums {
        dispatch(
            lanes,
            #[inline(always)]
            |lanes| self.render_lanes(lanes, scene, settings, camera, tile, samples),
        )
    }

    #[inline(always)]
    fn render_lanes(
        &self,
        lanes: Lanes,
        scene: &Scene,
        settings: &RenderSettings,
        camera: &Camera,
        tile: Tile,
        samples: Range<u32>,
    ) -> TileSums {
        let mut sums = TileSums::new(tile);
        let film = camera.film(settings.width, settings.height);
        let mut queue = Queue::new(settings, tile, samples);
        let mut paths = Paths::new();
        loop {
            // Every empty lane takes the next sample: its camera ray, which the step traces with
            // the other lanes' rays.
            for i in 0..W {
                if !paths.live[i]
                    && let Some((pixel, sampler, point)) = queue.next()
                {
                    let (o, d) = film.ray(point);
                    paths.start(i, pixel, sampler, o, d);
                }
            }
            if !paths.live.contains(&true) {
                return sums;
            }
            self.step(lanes, scene, settings, &mut paths, &mut sums);
        }
    }

    /// One vertex of every live path: its hit (or escape), emission, light sample and the
    /// BSDF-sampled direction on, as [`crate::estimator::nee::trace`] makes them.
    #[inline(always)]
    fn step(&self, lanes: Lanes, scene: &Scene, settings: &RenderSettings, paths: &mut Paths, sums: &mut TileSums) {
        let hit = self.intersect(scene, settings, paths, sums);
        let sp = Points::at(scene, &paths.o, &paths.d, &hit);
        let vertex = self.emission(scene, settings, &hit, &sp, paths, sums);
        let u = sampler::bounce_lanes(lanes, &paths.sampler, &paths.bounce, vertex.on);
        let light = self.light_sample(scene, settings, &sp, &vertex, &u);
        self.scatter(lanes, scene, settings, &sp, &vertex, &light, &u, paths, sums);
    }
}

/// What a step knows of each lane's vertex once its emission is counted: whether its path goes
/// on (`on`), and its Lambert lobe's reflectance and whether light sampling reaches it.
struct Vertex {
    on: [bool; W],
    diffuse: Rows,
    smooth: [bool; W],
}

/// `Vec3::dot`'s sum: `(x + y) + z`.
#[inline(always)]
pub(super) fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `a` where `c`, else `b`, lane by lane.
#[inline(always)]
pub(super) fn select(c: bool, a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    std::array::from_fn(|k| if c { a[k] } else { b[k] })
}

/// `Vec3::max_element`.
#[inline(always)]
pub(super) fn max3(v: [f32; 3]) -> f32 {
    let max = |a: f32, b: f32| if a > b { a } else { b };
    max(v[0], max(v[1], v[2]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::channels::Rgb;
    use crate::material::Material;
    use crate::mesh::MeshData;
    use crate::sampler::SamplerKind;
    use crate::scene::SceneBuilder;
    use crate::settings::Termination;
    use crate::tile::render_pixels;
    use glam::{Mat4, Vec4};

    /// A quad `corners` (counter-clockwise seen from its front) cut into `n` x `n` squares, with
    /// its normal at each vertex where `normals`.
    fn quad(corners: [Vec3; 4], n: u32, normals: bool, material: u32) -> MeshData {
        let [a, b, c, d] = corners;
        let at = |i: u32, j: u32| {
            let (u, v) = (i as f32 / n as f32, j as f32 / n as f32);
            (a * (1.0 - u) + b * u) * (1.0 - v) + (d * (1.0 - u) + c * u) * v
        };
        let mut mesh = MeshData { material, ..MeshData::default() };
        for j in 0..=n {
            for i in 0..=n {
                mesh.positions.push(at(i, j));
            }
        }
        for j in 0..n {
            for i in 0..n {
                let k = j * (n + 1) + i;
                mesh.indices.extend([k, k + 1, k + n + 2, k, k + n + 2, k + n + 1]);
            }
        }
        let normal = (b - a).cross(d - a).normalize();
        mesh.normals = normals.then(|| vec![normal; mesh.positions.len()]);
        mesh
    }

    /// A box from `lo` to `hi`, its faces outwards.
    fn cube(builder: &mut SceneBuilder, lo: Vec3, hi: Vec3, material: u32) {
        let p = |x: usize, y: usize, z: usize| Vec3::new([lo.x, hi.x][x], [lo.y, hi.y][y], [lo.z, hi.z][z]);
        let faces = [
            [p(0, 0, 1), p(1, 0, 1), p(1, 1, 1), p(0, 1, 1)],
            [p(1, 0, 0), p(0, 0, 0), p(0, 1, 0), p(1, 1, 0)],
            [p(0, 1, 1), p(1, 1, 1), p(1, 1, 0), p(0, 1, 0)],
            [p(1, 0, 1), p(0, 0, 1), p(0, 0, 0), p(1, 0, 0)],
            [p(1, 0, 1), p(1, 0, 0), p(1, 1, 0), p(1, 1, 1)],
            [p(0, 0, 0), p(0, 0, 1), p(0, 1, 1), p(0, 1, 0)],
        ];
        for face in faces {
            builder.add_mesh("box", quad(face, 1, false, material), Mat4::IDENTITY).unwrap();
        }
    }

    fn lambert(name: &str, rgb: Vec3) -> Material {
        let base_color = rgb.extend(1.0);
        Material { name: name.into(), base_color, metallic: 0.0, specular: 0.0, ..Material::default() }
    }

    /// A room open at the front (paths escape to a dim sky), a light under its ceiling and a
    /// small one glowing from both faces, two boxes; the floor cut into `floor` x `floor`
    /// squares (8 leaves 50 triangles, tested whole; 16 makes the rays walk a tree).
    fn room(floor: u32) -> Scene {
        let mut b = SceneBuilder::new();
        let white = b.add_material(lambert("white", Vec3::new(0.73, 0.71, 0.68)));
        let red = b.add_material(lambert("red", Vec3::new(0.63, 0.06, 0.05)));
        let light = b.add_material(Material { emissive: Vec3::new(17.0, 12.0, 4.0), ..lambert("light", Vec3::ONE) });
        let both = b.add_material(Material {
            emissive: Vec3::new(1.0, 2.0, 4.0),
            double_sided: true,
            ..lambert("both", Vec3::splat(0.5))
        });
        let v = Vec3::new;
        let walls = [
            ([v(-1., 0., 1.), v(1., 0., 1.), v(1., 0., -1.), v(-1., 0., -1.)], floor, true, white),
            ([v(-1., 2., -1.), v(1., 2., -1.), v(1., 2., 1.), v(-1., 2., 1.)], 1, false, white),
            ([v(-1., 0., -1.), v(1., 0., -1.), v(1., 2., -1.), v(-1., 2., -1.)], 1, true, white),
            ([v(-1., 0., 1.), v(-1., 0., -1.), v(-1., 2., -1.), v(-1., 2., 1.)], 1, false, red),
            ([v(1., 0., -1.), v(1., 0., 1.), v(1., 2., 1.), v(1., 2., -1.)], 1, true, white),
            ([v(-0.3, 1.98, -0.3), v(-0.3, 1.98, 0.3), v(0.3, 1.98, 0.3), v(0.3, 1.98, -0.3)], 1, false, light),
            ([v(0.5, 0.8, -0.9), v(0.9, 0.8, -0.9), v(0.9, 1.2, -0.9), v(0.5, 1.2, -0.9)], 1, false, both),
        ];
        for (corners, n, normals, material) in walls {
            b.add_mesh("wall", quad(corners, n, normals, material), Mat4::IDENTITY).unwrap();
        }
        cube(&mut b, v(-0.6, 0.0, -0.6), v(-0.1, 1.2, -0.1), white);
        cube(&mut b, v(0.1, 0.0, 0.1), v(0.6, 0.6, 0.6), red);
        b.environment = Vec3::splat(0.2);
        let mut scene = b.build();
        scene.cameras.push(Camera::framing(v(-1.0, 0.0, -1.0), v(1.0, 2.0, 1.0)));
        scene
    }

    fn settings(estimator: Estimator, sampler: SamplerKind, termination: Termination) -> RenderSettings {
        RenderSettings { seed: 5, estimator, sampler, termination, ..RenderSettings::new(24, 20) }
    }

    /// Every sample the wave renders has the bits the one-path estimator gives it, for both
    /// estimators, samplers and terminations, a transparent background, a tile off the image's
    /// corner and a run of samples not from zero, whether the rays test every triangle or walk,
    /// with its loops compiled for every instruction set this CPU has.
    #[test]
    fn the_wave_renders_every_sample_with_the_bits_of_one_path() {
        let mut checked = 0;
        for floor in [8, 16] {
            let scene = room(floor);
            for estimator in [Estimator::Mis, Estimator::Nee] {
                for sampler in [SamplerKind::Sobol, SamplerKind::Independent] {
                    for (termination, transparent) in [
                        (Termination::MaxBounces(4), false),
                        (Termination::RussianRoulette { from: 2, max_bounces: 7 }, true),
                    ] {
                        let mut s = settings(estimator, sampler, termination);
                        s.transparent = transparent;
                        let wave = Wave::for_render(&scene, &s).expect("a plain scene");
                        let camera = &scene.cameras[0];
                        let tile = Tile { x0: 5, y0: 3, width: 13, height: 11 };
                        let one_path = render_pixels(&scene, &s, camera, tile, 3..14, |_| Rgb);
                        for lanes in Lanes::ALL.into_iter().filter(|lanes| lanes.run_here()) {
                            let waved = wave.render_with(lanes, &scene, &s, camera, tile, 3..14);
                            let what = format!("{floor} {estimator:?} {sampler:?} {termination:?}, {lanes}");
                            assert_eq!(waved, one_path, "{what}");
                        }
                        checked += 1;
                    }
                }
            }
        }
        assert_eq!(checked, 16);
    }

    /// The wave takes plain scenes in RGB only: not the collision estimator, spectral light
    /// transport, a glossy material or vertex colours.
    #[test]
    fn the_wave_leaves_other_scenes_to_one_path() {
        let scene = room(1);
        let s = settings(Estimator::Mis, SamplerKind::Sobol, Termination::MaxBounces(3));
        assert!(Wave::for_render(&scene, &s).is_some());
        let collision = RenderSettings { estimator: Estimator::Collision, ..s.clone() };
        assert!(Wave::for_render(&scene, &collision).is_none());
        let spectral = RenderSettings { color: ColorMode::Spectral, ..s.clone() };
        assert!(Wave::for_render(&scene, &spectral).is_none());
        let mut glossy = room(1);
        glossy.surfaces.materials_mut()[0].specular = 1.0;
        assert!(Wave::for_render(&glossy, &s).is_none(), "a specular layer");
        let mut b = SceneBuilder::new();
        let white = b.add_material(lambert("white", Vec3::ONE));
        let mut mesh = quad([Vec3::X, Vec3::Y, Vec3::Z, Vec3::ONE], 1, false, white);
        mesh.colors = Some(vec![Vec4::ONE; mesh.positions.len()]);
        b.add_mesh("coloured", mesh, Mat4::IDENTITY).unwrap();
        assert!(Wave::for_render(&b.build(), &s).is_none(), "vertex colours");
    }
}
