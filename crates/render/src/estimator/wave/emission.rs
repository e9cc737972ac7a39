//! The wave's second stage: what each hit emits towards the path (weighted against the light
//! sample that could have found it), and which paths go on.

use super::intersect::Points;
use super::paths::{Paths, Rows};
use super::{Vertex, W, Wave};
use crate::interaction::Hit;
use crate::scene::Scene;
use crate::settings::RenderSettings;
use crate::sums::TileSums;

impl Wave {
    /// Adds each hit's emission to its path; a path at its last bounce ends. The others go on
    /// with their material's lobe.
    #[inline(always)]
    pub(super) fn emission(
        &self,
        scene: &Scene,
        settings: &RenderSettings,
        hit: &[Option<Hit>; W],
        sp: &Points,
        paths: &mut Paths,
        sums: &mut TileSums,
    ) -> Vertex {
        let lights = &scene.lights;
        let max = settings.max_bounces();
        let mut on = [false; W];
        let mut diffuse = Rows::default();
        let mut smooth = [false; W];
        for i in 0..W {
            let Some(h) = hit[i] else { continue };
            let Some(material) = &self.materials[sp.material[i] as usize] else {
                unreachable!("every material a triangle uses is plain (`Wave::for_render`)")
            };
            let bounce = paths.bounce[i];
            if let Some(le) = material.emission.filter(|_| sp.front_face[i] || material.double_sided)
                && le.max_element() > 0.0
            {
                paths.saw_emitter[i] |= bounce == 0;
                let w = if paths.prev_delta[i] {
                    1.0
                } else {
                    let (p, ng) = (sp.p.get(i), sp.ng.get(i));
                    let (prev_p, prev_n) = (paths.prev_p.get(i), paths.prev_n.get(i));
                    self.combination.weight(
                        paths.prev_pdf[i],
                        || lights.triangle_pdf_at(prev_p, prev_n, h.triangle, p, ng, settings.lights),
                        false,
                    )
                };
                paths.l.set(i, paths.l.get(i) + paths.beta.get(i) * le * w);
            }
            if bounce == max {
                paths.finish(i, sums);
                continue;
            }
            diffuse.set(i, material.bsdf.diffuse);
            smooth[i] = material.smooth;
            on[i] = true;
        }
        Vertex { on, diffuse, smooth }
    }
}
