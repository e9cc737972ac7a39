//! glTF animations: keyframe channels read and checked once, then sampled at any time (pure
//! functions of the keys and the time). The interpolation follows the glTF 2.0 specification,
//! section 3.11 and Appendix C: STEP holds a key's value until the next key; LINEAR blends
//! translations, scales and weights linearly and rotations by slerp of unit quaternions, the
//! shorter way; CUBICSPLINE is the cubic Hermite spline whose in- and out-tangents are scaled by
//! the key interval, quaternions normalised after. Before the first key a channel holds its first
//! value, after the last its last.

use std::fmt;

/// What a channel moves.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Property {
    Translation,
    Rotation,
    Scale,
    /// Morph target weights: one value per target.
    Weights,
}

impl Property {
    pub fn name(self) -> &'static str {
        match self {
            Property::Translation => "translation",
            Property::Rotation => "rotation",
            Property::Scale => "scale",
            Property::Weights => "weights",
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Interpolation {
    Step,
    Linear,
    CubicSpline,
}

impl Interpolation {
    pub fn name(self) -> &'static str {
        match self {
            Interpolation::Step => "STEP",
            Interpolation::Linear => "LINEAR",
            Interpolation::CubicSpline => "CUBICSPLINE",
        }
    }
}

/// One animated property of one node: key times (finite, strictly increasing) and the values
/// at them, `width` floats a value (3, 4, or the number of morph targets); CUBICSPLINE keys hold
/// three values each, in-tangent, value and out-tangent.
#[derive(Clone, Debug)]
pub struct Channel {
    pub node: usize,
    pub property: Property,
    pub interpolation: Interpolation,
    pub times: Vec<f32>,
    pub values: Vec<f32>,
    pub width: usize,
}

/// One glTF animation: its channels, named by its index and name.
#[derive(Clone, Debug)]
pub struct Clip {
    pub index: usize,
    pub name: String,
    pub channels: Vec<Channel>,
}

impl Clip {
    /// From the first key of any channel to the last of any, in seconds (0, 0 without keys).
    pub fn range(&self) -> (f32, f32) {
        let first = self.channels.iter().filter_map(|c| c.times.first().copied()).reduce(f32::min);
        let last = self.channels.iter().filter_map(|c| c.times.last().copied()).reduce(f32::max);
        (first.unwrap_or(0.0), last.unwrap_or(0.0))
    }

    /// How long the clip plays from time 0: its last key's time.
    pub fn duration(&self) -> f32 {
        self.range().1
    }
}

impl fmt::Display for Clip {
    /// "0 'Walk': 57 channels (translation, rotation, scale; LINEAR), keys 0.042-2.000 s (frames
    /// 0-48 at 24 fps)"
    fn fmt(&self, f: &mut fmt::Formatter) -> fmt::Result {
        let mut properties: Vec<&str> = Vec::new();
        let mut interpolations: Vec<&str> = Vec::new();
        for c in &self.channels {
            if !properties.contains(&c.property.name()) {
                properties.push(c.property.name());
            }
            if !interpolations.contains(&c.interpolation.name()) {
                interpolations.push(c.interpolation.name());
            }
        }
        let (first, last) = self.range();
        let name = if self.name.is_empty() { "(unnamed)".to_string() } else { format!("'{}'", self.name) };
        write!(
            f,
            "{} {name}: {} channel{} ({}; {}), keys {first:.3}-{last:.3} s (frames 0-{} at 24 fps)",
            self.index,
            self.channels.len(),
            if self.channels.len() == 1 { "" } else { "s" },
            properties.join(", "),
            interpolations.join(", "),
            libm::ceil(last as f64 * 24.0 - 1e-3) as u64
        )
    }
}

/// Which animations play: glTF files may hold several, and nothing in the format says which one
/// is meant; the first is the usual choice, `All` plays every one on one clock.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum Choice {
    #[default]
    First,
    All,
    Index(usize),
    Name(String),
}

impl Choice {
    /// `all`, an index, or a name, as `--animation` takes it.
    pub fn parse(s: &str) -> Choice {
        match s {
            "all" => Choice::All,
            _ => s.parse().map(Choice::Index).unwrap_or_else(|_| Choice::Name(s.to_string())),
        }
    }

    /// The indices of the animations chosen among those named `names` (in file order), or an
    /// error that lists what there is.
    pub fn pick(&self, names: &[&str]) -> Result<Vec<usize>, String> {
        let listed = || {
            if names.is_empty() {
                "the scene has no animations".to_string()
            } else {
                let names: Vec<String> = names
                    .iter()
                    .enumerate()
                    .map(|(i, n)| if n.is_empty() { format!("{i} (unnamed)") } else { format!("{i} '{n}'") })
                    .collect();
                format!("the scene's animations are {}", names.join(", "))
            }
        };
        match self {
            Choice::First => Ok((0..names.len().min(1)).collect()),
            Choice::All => Ok((0..names.len()).collect()),
            Choice::Index(i) if *i < names.len() => Ok(vec![*i]),
            Choice::Index(i) => Err(format!("no animation {i}: {}", listed())),
            Choice::Name(name) => {
                let found: Vec<usize> = (0..names.len()).filter(|&i| names[i] == name).collect();
                if found.is_empty() { Err(format!("no animation named '{name}': {}", listed())) } else { Ok(found) }
            }
        }
    }
}

impl Choice {
    /// The protocol's spelling (`Pose.animation`): "" the first, "*" all, "#N", "=NAME".
    pub fn to_wire(&self) -> String {
        match self {
            Choice::First => String::new(),
            Choice::All => "*".into(),
            Choice::Index(i) => format!("#{i}"),
            Choice::Name(n) => format!("={n}"),
        }
    }

    pub fn from_wire(s: &str) -> Result<Choice, String> {
        if s.len() > 1024 {
            return Err(format!("an animation name of {} bytes", s.len()));
        }
        match s.split_at_checked(1) {
            None => Ok(Choice::First),
            Some(("*", "")) => Ok(Choice::All),
            Some(("#", n)) => n.parse().map(Choice::Index).map_err(|_| format!("'{s}' names no animation index")),
            Some(("=", name)) => Ok(Choice::Name(name.to_string())),
            _ => Err(format!("'{s}' is not an animation choice")),
        }
    }
}

impl fmt::Display for Choice {
    fn fmt(&self, f: &mut fmt::Formatter) -> fmt::Result {
        match self {
            Choice::First => write!(f, "first"),
            Choice::All => write!(f, "all"),
            Choice::Index(i) => write!(f, "{i}"),
            Choice::Name(n) => write!(f, "{n}"),
        }
    }
}

impl Channel {
    /// Checks the keys: at least one, times finite and strictly increasing, values finite and as
    /// many as the times ask for. `what` names the channel in the error.
    pub fn check(&self, what: &str) -> Result<(), String> {
        if self.times.is_empty() {
            return Err(format!("{what}: no keyframes"));
        }
        if let Some(i) = self.times.iter().position(|t| !t.is_finite()) {
            return Err(format!("{what}: key time {i} is {}, not a finite number", self.times[i]));
        }
        if let Some(i) = self.times.windows(2).position(|w| w[1] <= w[0]) {
            return Err(format!(
                "{what}: key times must increase, but key {} is at {} s after key {i} at {} s",
                i + 1,
                self.times[i + 1],
                self.times[i]
            ));
        }
        let per_key = self.width * if self.interpolation == Interpolation::CubicSpline { 3 } else { 1 };
        if self.width == 0 || self.values.len() != self.times.len() * per_key {
            return Err(format!(
                "{what}: {} output values for {} keys of {} {} value(s) of {} component(s)",
                self.values.len(),
                self.times.len(),
                self.interpolation.name(),
                self.property.name(),
                self.width
            ));
        }
        if let Some(i) = self.values.iter().position(|v| !v.is_finite()) {
            return Err(format!("{what}: output value {i} is {}, not a finite number", self.values[i]));
        }
        Ok(())
    }

    /// The channel's value at time `t` (seconds), `width` floats.
    pub fn sample(&self, t: f32) -> Vec<f32> {
        let n = self.times.len();
        let w = self.width;
        let cubic = self.interpolation == Interpolation::CubicSpline;
        // Key k's value (the middle of a CUBICSPLINE triplet), in-tangent and out-tangent.
        let value = |k: usize| {
            if cubic { &self.values[(3 * k + 1) * w..(3 * k + 2) * w] } else { &self.values[k * w..(k + 1) * w] }
        };
        let in_tangent = |k: usize| &self.values[3 * k * w..(3 * k + 1) * w];
        let out_tangent = |k: usize| &self.values[(3 * k + 2) * w..(3 * k + 3) * w];
        // A NaN time holds the first value too.
        if t <= self.times[0] || t.is_nan() {
            return value(0).to_vec();
        }
        if t >= self.times[n - 1] {
            return value(n - 1).to_vec();
        }
        // times[k] <= t < times[k + 1].
        let k = self.times.partition_point(|&key| key <= t) - 1;
        let (t0, t1) = (self.times[k], self.times[k + 1]);
        let dt = t1 - t0;
        let s = (t - t0) / dt;
        let rotation = self.property == Property::Rotation;
        match self.interpolation {
            Interpolation::Step => value(k).to_vec(),
            Interpolation::Linear if rotation => slerp(value(k), value(k + 1), s).to_vec(),
            Interpolation::Linear => value(k).iter().zip(value(k + 1)).map(|(&a, &b)| lerp(a, b, s)).collect(),
            Interpolation::CubicSpline => {
                let out: Vec<f32> = (0..w)
                    .map(|i| hermite(value(k)[i], out_tangent(k)[i], value(k + 1)[i], in_tangent(k + 1)[i], dt, s))
                    .collect();
                if rotation { normalize4(&out).to_vec() } else { out }
            }
        }
    }
}

/// `(1 - s) a + s b`, as the specification writes it.
pub fn lerp(a: f32, b: f32, s: f32) -> f32 {
    (1.0 - s) * a + s * b
}

/// The cubic Hermite spline of glTF's Appendix C between value `v0` with out-tangent `b0` and
/// value `v1` with in-tangent `a1`, the tangents scaled by the key interval `dt`, at `s` in [0, 1].
pub fn hermite(v0: f32, b0: f32, v1: f32, a1: f32, dt: f32, s: f32) -> f32 {
    let s2 = s * s;
    let s3 = s2 * s;
    (2.0 * s3 - 3.0 * s2 + 1.0) * v0 + (s3 - 2.0 * s2 + s) * dt * b0 + (-2.0 * s3 + 3.0 * s2) * v1 + (s3 - s2) * dt * a1
}

/// Spherical linear interpolation of unit quaternions (x, y, z, w) the shorter way round: when
/// they lie more than 90 degrees apart on the 4-sphere, `b` is negated (the same rotation).
/// Nearly equal quaternions are blended linearly and normalised, where slerp's division by
/// `sin(angle)` would lose its precision.
pub fn slerp(a: &[f32], b: &[f32], s: f32) -> [f32; 4] {
    let mut d = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3];
    let sign = if d < 0.0 { -1.0 } else { 1.0 };
    d *= sign;
    let b = [sign * b[0], sign * b[1], sign * b[2], sign * b[3]];
    if d > 0.9995 {
        let q: Vec<f32> = (0..4).map(|i| lerp(a[i], b[i], s)).collect();
        return normalize4(&q);
    }
    let angle = libm::acosf(d.min(1.0));
    let sin_angle = libm::sinf(angle);
    let wa = libm::sinf((1.0 - s) * angle) / sin_angle;
    let wb = libm::sinf(s * angle) / sin_angle;
    [wa * a[0] + wb * b[0], wa * a[1] + wb * b[1], wa * a[2] + wb * b[2], wa * a[3] + wb * b[3]]
}

/// `q / |q|`; the identity rotation for a zero quaternion.
pub fn normalize4(q: &[f32]) -> [f32; 4] {
    let len = libm::sqrtf(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    if len > 0.0 && len.is_finite() { [q[0] / len, q[1] / len, q[2] / len, q[3] / len] } else { [0.0, 0.0, 0.0, 1.0] }
}

/// A node's local transform and morph weights at one time: its stored values where no channel
/// moves them.
#[derive(Clone, Debug, PartialEq)]
pub struct NodePose {
    pub translation: [f32; 3],
    pub rotation: [f32; 4],
    pub scale: [f32; 3],
    pub weights: Option<Vec<f32>>,
}

/// Applies the chosen clips at time `t` to `nodes` (each node's stored pose). Channels apply in
/// clip order and then channel order, so where two move one property the later wins.
pub fn pose(clips: &[&Clip], t: f32, nodes: &mut [NodePose]) {
    for clip in clips {
        for c in &clip.channels {
            let Some(node) = nodes.get_mut(c.node) else { continue };
            let v = c.sample(t);
            match c.property {
                Property::Translation => node.translation = [v[0], v[1], v[2]],
                Property::Rotation => node.rotation = [v[0], v[1], v[2], v[3]],
                Property::Scale => node.scale = [v[0], v[1], v[2]],
                Property::Weights => node.weights = Some(v),
            }
        }
    }
}

/// The image header lines of a posed render: the animation, the time, and for a frame of a
/// sequence its number, the frames per second and the frame's seed. One function writes them for
/// `tessera render` and the farm, so that their images are the same files.
pub fn header_lines(animation: &Choice, time: f32, frame: Option<(u32, f64, u64)>) -> String {
    let mut out = format!("animation={animation}\ntime={time}\n");
    if let Some((f, fps, seed)) = frame {
        out += &format!("frame={f}\nfps={fps}\nframe_seed={seed}\n");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn channel(
        property: Property,
        interpolation: Interpolation,
        times: &[f32],
        values: &[f32],
        width: usize,
    ) -> Channel {
        Channel { node: 0, property, interpolation, times: times.to_vec(), values: values.to_vec(), width }
    }

    #[test]
    fn values_hold_outside_the_keys_and_step_holds_between_them() {
        let c = channel(Property::Translation, Interpolation::Step, &[1.0, 2.0], &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0], 3);
        assert_eq!(c.sample(0.0), [1.0, 2.0, 3.0]);
        assert_eq!(c.sample(f32::NAN), [1.0, 2.0, 3.0]);
        assert_eq!(c.sample(1.999), [1.0, 2.0, 3.0]);
        assert_eq!(c.sample(2.0), [4.0, 5.0, 6.0]);
        assert_eq!(c.sample(9.0), [4.0, 5.0, 6.0]);
    }

    #[test]
    fn slerp_takes_the_shorter_way_and_keeps_unit_length() {
        // A quarter turn about z to its negation's neighbour: -identity is the identity rotation.
        let h = libm::sqrtf(0.5);
        let a = [0.0, 0.0, h, h];
        let b = [0.0, 0.0, 0.0, -1.0];
        let q = slerp(&a, &b, 0.5);
        // Halfway between 90 and 0 degrees about z is 45 degrees, not 225.
        let expected = [0.0, 0.0, libm::sinf(std::f32::consts::PI / 8.0), libm::cosf(std::f32::consts::PI / 8.0)];
        for i in 0..4 {
            assert!((q[i] - expected[i]).abs() < 1e-6, "{q:?} vs {expected:?}");
        }
        assert!((q.iter().map(|x| x * x).sum::<f32>() - 1.0).abs() < 1e-6);
    }

    #[test]
    fn cubic_splines_pass_through_their_keys_with_their_tangents() {
        // One component, keys at 0 and 2 with values 0 and 1, out-tangent 3 and in-tangent -1.
        let c =
            channel(Property::Weights, Interpolation::CubicSpline, &[0.0, 2.0], &[9.0, 0.0, 3.0, -1.0, 1.0, 9.0], 1);
        assert_eq!(c.sample(0.0), [0.0]);
        assert_eq!(c.sample(2.0), [1.0]);
        // The slope at the start is the out-tangent: p'(0) = dt b0 / dt = 3.
        let h = 1e-3;
        let slope = (c.sample(h)[0] - c.sample(0.0)[0]) / h;
        assert!((slope - 3.0).abs() < 0.01, "slope {slope}");
        let slope_end = (c.sample(2.0)[0] - c.sample(2.0 - h)[0]) / h;
        assert!((slope_end + 1.0).abs() < 0.01, "slope {slope_end}");
    }

    #[test]
    fn bad_keys_are_refused_with_what_is_wrong() {
        let c = |times: &[f32], values: &[f32]| {
            channel(Property::Scale, Interpolation::Linear, times, values, 3).check("x")
        };
        assert!(c(&[0.0, 1.0], &[1.0; 6]).is_ok());
        assert!(c(&[], &[]).unwrap_err().contains("no keyframes"));
        assert!(c(&[1.0, 1.0], &[1.0; 6]).unwrap_err().contains("must increase"));
        assert!(c(&[1.0, 0.5], &[1.0; 6]).unwrap_err().contains("must increase"));
        assert!(c(&[0.0, f32::INFINITY], &[1.0; 6]).unwrap_err().contains("not a finite"));
        assert!(c(&[0.0, 1.0], &[1.0; 5]).unwrap_err().contains("5 output values for 2 keys"));
        let mut v = [1.0; 6];
        v[4] = f32::NAN;
        assert!(c(&[0.0, 1.0], &v).unwrap_err().contains("output value 4"));
    }

    #[test]
    fn choices_pick_by_index_name_or_all() {
        let names = ["Walk", "Run"];
        assert_eq!(Choice::parse("1"), Choice::Index(1));
        assert_eq!(Choice::parse("all"), Choice::All);
        assert_eq!(Choice::parse("Run").pick(&names).unwrap(), [1]);
        assert_eq!(Choice::First.pick(&names).unwrap(), [0]);
        assert_eq!(Choice::All.pick(&names).unwrap(), [0, 1]);
        let err = Choice::parse("Jump").pick(&names).unwrap_err();
        assert!(err.contains("no animation named 'Jump'") && err.contains("1 'Run'"), "{err}");
        assert!(Choice::Index(2).pick(&names).is_err());
        assert!(Choice::First.pick(&[]).unwrap().is_empty());
        assert!(Choice::Index(0).pick(&[]).unwrap_err().contains("has no animations"));
    }

    #[test]
    fn choices_travel_as_they_are() {
        for c in [Choice::First, Choice::All, Choice::Index(3), Choice::Name("#1".into()), Choice::Name(String::new())]
        {
            assert_eq!(Choice::from_wire(&c.to_wire()).unwrap(), c);
        }
        assert!(Choice::from_wire("x").is_err());
        assert!(Choice::from_wire("#-1").is_err());
    }
}
