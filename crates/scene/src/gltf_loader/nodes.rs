//! The node tree and what moves it: every node's local pose from the chosen animations at a
//! time, its world transform, the scene built at a pose ([`Parsed::pose`]), and the animation
//! clips read from the file.

use super::cameras::{convert_camera, convert_light, describe_camera};
use super::geometry::{add_mesh, items, read_floats, read_scalars};
use super::materials::Materials;
use super::skins::{Pose, joint_matrices};
use super::{Parsed, Placed};
use crate::animation::{Channel, Clip, Interpolation, NodePose, Property};
use crate::{LoadError, LoadedScene, PoseAt};
use tessera_render::glam::Mat4;
use tessera_render::{Material, SceneBuilder};

impl Parsed {
    /// Every node's local pose at `at` (its stored translation, rotation, scale and morph weights
    /// where no chosen channel moves them), and whether a chosen channel moves it.
    pub fn node_poses(&self, at: &PoseAt) -> Result<(Vec<NodePose>, Vec<bool>), String> {
        let names: Vec<&str> = self.document.animations().map(|a| a.name().unwrap_or("")).collect();
        let chosen: Vec<&Clip> = at
            .animation
            .pick(&names)?
            .into_iter()
            .map(|i| self.clips[i].as_ref().map_err(String::clone))
            .collect::<Result<_, _>>()?;
        let mut nodes: Vec<NodePose> = self
            .document
            .nodes()
            .map(|n| {
                let (translation, rotation, scale) = n.transform().decomposed();
                NodePose { translation, rotation, scale, weights: None }
            })
            .collect();
        let mut animated = vec![false; nodes.len()];
        for c in chosen.iter().flat_map(|c| &c.channels) {
            animated[c.node] = true;
        }
        crate::animation::pose(&chosen, at.time, &mut nodes);
        Ok((nodes, animated))
    }

    /// Every node's world transform at `at` (at rest for `None`), in the order the scene is
    /// built. A node no chosen channel moves keeps its stored matrix, so that a still render has
    /// the bits it had before animation existed; a moved one gets the matrix glTF composes from
    /// translation, rotation and scale, by the glTF crate's own arithmetic, as a static node with
    /// those values would.
    /// The index of material variant `name`, or what the file offers instead.
    pub fn variant_index(&self, name: &str) -> Result<usize, String> {
        let names = &self.info.variants;
        names.iter().position(|v| v == name).ok_or_else(|| match names.len() {
            0 => format!("there is no material variant '{name}': the file has none"),
            _ => format!("there is no material variant '{name}' (the file has: {})", names.join(", ")),
        })
    }

    pub fn place(&self, at: Option<&PoseAt>) -> Result<Placed, String> {
        let all: Vec<gltf::Node> = self.document.nodes().collect();
        let (poses, animated) = match at {
            Some(at) => self.node_poses(at)?,
            None => (Vec::new(), vec![false; all.len()]),
        };
        let local = |node: &gltf::Node| -> Mat4 {
            let i = node.index();
            if !animated[i] {
                return Mat4::from_cols_array_2d(&node.transform().matrix());
            }
            let p = &poses[i];
            let trs =
                gltf::scene::Transform::Decomposed { translation: p.translation, rotation: p.rotation, scale: p.scale };
            Mat4::from_cols_array_2d(&trs.matrix())
        };
        let mut worlds: Vec<Option<Mat4>> = vec![None; all.len()];
        let mut order = Vec::new();
        let mut stack: Vec<(usize, Mat4, u32)> = self.roots.iter().map(|&i| (i, Mat4::IDENTITY, 0)).collect();
        while let Some((i, parent, depth)) = stack.pop() {
            if depth > 256 {
                return Err("node hierarchy deeper than 256 levels (a cycle?)".into());
            }
            let world = parent * local(&all[i]);
            worlds[i].get_or_insert(world);
            stack.extend(all[i].children().map(|c| (c.index(), world, depth + 1)));
            order.push(i);
        }
        Ok(Placed { worlds, order, poses })
    }

    /// What building the scene at `at` with material variant `variant` would make, checked and
    /// counted without building anything: the pose's animations exist and their keys are sound,
    /// the variant exists; the triangles the node tree draws, the cameras it holds (at least the
    /// one that frames a scene without any), the texels its images decoded to.
    pub fn census(&self, at: Option<&PoseAt>, variant: Option<&str>) -> Result<crate::Census, String> {
        if let Some(v) = variant {
            self.variant_index(v)?;
        }
        let placed = self.place(at)?;
        let all: Vec<gltf::Node> = self.document.nodes().collect();
        let cameras = placed.order.iter().filter(|&&i| all[i].camera().is_some()).count();
        Ok(crate::Census {
            drawn_triangles: self.drawn_triangles,
            cameras: cameras.max(1),
            texels: self.images.iter().map(|i| i.width as u64 * i.height as u64).sum(),
            map_texels: 0,
        })
    }

    /// The scene posed by `at`'s animations at its time, or at rest (every node as stored) for
    /// `None`.
    /// The scene at `at` (at rest: `None`) with material variant `variant` (an index into
    /// `info.variants`; `None`: the primitives' own materials).
    pub fn pose(&self, at: Option<&PoseAt>, variant: Option<usize>) -> Result<LoadedScene, LoadError> {
        let content = |message: String| LoadError::Content { path: self.path.clone(), message };
        let document = &self.document;
        let buffers = &self.buffers[..];
        let mut info = self.info.clone();
        let placed = self.place(at).map_err(content)?;
        let mut builder = SceneBuilder::new();
        builder.images = self.images.clone();
        builder.textures = self.textures.clone();
        for m in &self.materials {
            builder.add_material(m.clone());
        }
        let default_material = builder.add_material(Material::default());
        let all: Vec<gltf::Node> = document.nodes().collect();
        let worlds = &placed.worlds;
        for &i in &placed.order {
            let (node, world) = (&all[i], worlds[i].unwrap_or(Mat4::IDENTITY));
            if let Some(mesh) = node.mesh() {
                let joints = node.skin().map(|s| joint_matrices(&s, worlds, buffers)).transpose().map_err(content)?;
                let weights = match placed.poses.get(i).and_then(|p| p.weights.as_deref()) {
                    Some(w) => w,
                    None => node.weights().or(mesh.weights()).unwrap_or(&[]),
                };
                let pose = Pose { world, joints: joints.as_deref(), weights };
                let materials = Materials { default: default_material, count: self.materials.len(), variant };
                add_mesh(&mut builder, &mesh, &pose, buffers, materials, &mut info).map_err(content)?;
            }
            if let Some(camera) = node.camera() {
                let cam = convert_camera(&camera, world, builder.cameras.len()).map_err(content)?;
                info.cameras.push(describe_camera(&cam));
                builder.cameras.push(cam);
            }
            if let Some(light) = node.light() {
                let name = light.name().unwrap_or("").to_string();
                match convert_light(&light, world) {
                    Some(l) => {
                        info.punctual_lights.push(format!("{} '{name}'", l.kind()));
                        builder.punctual.push(l);
                    }
                    None => info
                        .warnings
                        .push(format!("light '{name}' has a non-finite position, direction or intensity: skipped")),
                }
            }
        }
        if builder.degenerate_triangles > 0 {
            info.warnings.push(format!("{} degenerate (zero-area) triangles skipped", builder.degenerate_triangles));
        }
        info.triangles = builder.triangle_count();
        info.materials = document.materials().len();
        let scene = builder.build();
        Ok(LoadedScene { scene, hash: self.hash.clone(), info })
    }
}

/// Reads and checks one animation's channels. Channels that target a property glTF does not
/// define here (KHR_animation_pointer's "pointer") are skipped.
pub(super) fn read_clip(a: &gltf::Animation, buffers: &[gltf::buffer::Data]) -> Result<Clip, String> {
    use gltf::animation::Property as P;
    let name = a.name().unwrap_or("").to_string();
    let mut channels = Vec::new();
    for (k, c) in a.channels().enumerate() {
        let sampler = c.sampler();
        let (input, output) = (sampler.input(), sampler.output());
        let what = format!(
            "animation {} '{name}' channel {k} (input accessor {}, output accessor {})",
            a.index(),
            input.index(),
            output.index()
        );
        let node = c.target().node();
        let property = match c.target().property() {
            P::Translation => Property::Translation,
            P::Rotation => Property::Rotation,
            P::Scale => Property::Scale,
            P::MorphTargetWeights => Property::Weights,
        };
        let interpolation = match sampler.interpolation() {
            gltf::animation::Interpolation::Step => Interpolation::Step,
            gltf::animation::Interpolation::Linear => Interpolation::Linear,
            gltf::animation::Interpolation::CubicSpline => Interpolation::CubicSpline,
        };
        if input.data_type() != gltf::accessor::DataType::F32
            || input.dimensions() != gltf::accessor::Dimensions::Scalar
        {
            return Err(format!("{what}: key times must be float scalars"));
        }
        let times: Vec<f32> = items::<f32>(&input, buffers).map_err(|e| format!("{what}: {e}"))?;
        let (values, width): (Vec<f32>, usize) = match property {
            Property::Translation | Property::Scale => {
                (read_floats::<3>(&output, buffers).map_err(|e| format!("{what}: {e}"))?.concat(), 3)
            }
            Property::Rotation => (read_floats::<4>(&output, buffers).map_err(|e| format!("{what}: {e}"))?.concat(), 4),
            Property::Weights => {
                let targets =
                    node.mesh().and_then(|m| m.primitives().map(|p| p.morph_targets().len()).max()).unwrap_or(0);
                if targets == 0 {
                    return Err(format!(
                        "{what}: animates the weights of node {}, which has no morph targets",
                        node.index()
                    ));
                }
                (read_scalars(&output, buffers).map_err(|e| format!("{what}: {e}"))?, targets)
            }
        };
        let channel = Channel { node: node.index(), property, interpolation, times, values, width };
        channel.check(&what)?;
        channels.push(channel);
    }
    Ok(Clip { index: a.index(), name, channels })
}
