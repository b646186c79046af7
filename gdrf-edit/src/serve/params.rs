//! What a request asks for, read from its query string: every value is checked here, and a
//! bad one is an [`ApiError`] (400) whose message names the parameter and the value.
use std::collections::HashMap;

/// An HTTP error the client sees: a status and a message naming what was wrong.
#[derive(Debug, Clone, PartialEq)]
pub struct ApiError {
    pub status: u16,
    pub message: String,
}

impl ApiError {
    pub fn bad(message: impl Into<String>) -> Self {
        Self { status: 400, message: message.into() }
    }
    pub fn not_found(message: impl Into<String>) -> Self {
        Self { status: 404, message: message.into() }
    }
}

/// Where a shape or an appearance comes from, as a request names it.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum SourceSpec {
    /// `seed:N`, N a non-negative integer.
    Seed(i64),
    /// `features:NAME`: a file of the `--features` folder, by its name alone.
    Features(String),
    /// `photo:ID`: an uploaded photo's inverted features, by the id the upload returned.
    Photo(u64),
}

impl std::fmt::Display for SourceSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Seed(s) => write!(f, "seed:{s}"),
            Self::Features(n) => write!(f, "features:{n}"),
            Self::Photo(id) => write!(f, "photo:{id}"),
        }
    }
}

impl SourceSpec {
    /// Parses parameter `key`'s value `v`.
    pub fn parse(key: &str, v: &str) -> Result<Self, ApiError> {
        let bad = |why: &str| ApiError::bad(format!("{key} '{v}': {why}; expected seed:N, features:NAME or photo:ID"));
        if let Some(n) = v.strip_prefix("seed:") {
            return match n.parse::<i64>() {
                Ok(s) if s >= 0 => Ok(Self::Seed(s)),
                _ => Err(bad("the seed must be a non-negative integer")),
            };
        }
        if let Some(name) = v.strip_prefix("features:") {
            // A name, never a path: the file is looked up among the folder's own entries.
            let plain = !name.is_empty()
                && name.chars().all(|c| c.is_ascii_alphanumeric() || "._-".contains(c))
                && !name.starts_with('.');
            return if plain { Ok(Self::Features(name.to_string())) } else { Err(bad("not a plain file name")) };
        }
        if let Some(id) = v.strip_prefix("photo:") {
            return id.parse().map(Self::Photo).map_err(|_| bad("the id is not a number"));
        }
        Err(bad("unknown kind of source"))
    }
}

/// A query string's parameters (percent-decoded; `+` is a space).
pub struct Query(HashMap<String, String>);

fn decode(s: &str) -> Result<String, ApiError> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'%' => {
                let hex = s.get(i + 1..i + 3).and_then(|h| u8::from_str_radix(h, 16).ok());
                out.push(hex.ok_or_else(|| ApiError::bad(format!("the query '{s}' has a bad percent escape")))?);
                i += 3;
            }
            b'+' => {
                out.push(b' ');
                i += 1;
            }
            c => {
                out.push(c);
                i += 1;
            }
        }
    }
    String::from_utf8(out).map_err(|_| ApiError::bad(format!("the query '{s}' is not UTF-8")))
}

impl Query {
    pub fn parse(url: &str) -> Result<Self, ApiError> {
        let mut map = HashMap::new();
        if let Some((_, q)) = url.split_once('?') {
            for pair in q.split('&').filter(|p| !p.is_empty()) {
                let (k, v) = pair.split_once('=').unwrap_or((pair, ""));
                map.insert(decode(k)?, decode(v)?);
            }
        }
        Ok(Self(map))
    }

    pub fn get(&self, key: &str) -> Option<&str> {
        self.0.get(key).map(String::as_str)
    }

    /// A number in `range`, or `default` when absent.
    pub fn number(&self, key: &str, default: f64, range: (f64, f64), unit: &str) -> Result<f64, ApiError> {
        let Some(v) = self.get(key) else { return Ok(default) };
        match v.parse::<f64>() {
            Ok(x) if x.is_finite() && (range.0..=range.1).contains(&x) => Ok(x),
            _ => Err(ApiError::bad(format!("{key} '{v}': expected {unit} from {} to {}", range.0, range.1))),
        }
    }

    /// An integer in `range`, or `default` when absent.
    pub fn integer(&self, key: &str, default: i64, range: (i64, i64), unit: &str) -> Result<i64, ApiError> {
        let Some(v) = self.get(key) else { return Ok(default) };
        match v.parse::<i64>() {
            Ok(x) if (range.0..=range.1).contains(&x) => Ok(x),
            _ => Err(ApiError::bad(format!("{key} '{v}': expected {unit} from {} to {}", range.0, range.1))),
        }
    }

    /// A source (required when `default` is None).
    pub fn source(&self, key: &str, default: Option<SourceSpec>) -> Result<SourceSpec, ApiError> {
        match (self.get(key), default) {
            (Some(v), _) => SourceSpec::parse(key, v),
            (None, Some(d)) => Ok(d),
            (None, None) => Err(ApiError::bad(format!("{key}: missing; expected seed:N, features:NAME or photo:ID"))),
        }
    }

    /// An optional second source and the fraction of the way toward it.
    pub fn blend(&self, key: &str) -> Result<Option<(SourceSpec, f64)>, ApiError> {
        let t = self.number(&format!("{key}_t"), 0.0, (0.0, 1.0), "a fraction")?;
        match self.get(&format!("{key}_b")) {
            Some(v) if !v.is_empty() => Ok(Some((SourceSpec::parse(&format!("{key}_b"), v)?, t))),
            _ => Ok(None),
        }
    }
}

/// The limits a server was started with and the defaults of its model.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub max_resolution: i64,
    pub max_samples: i64,
    pub default_resolution: i64,
    pub default_samples: i64,
    /// The camera's field of view and mean pitch, in degrees.
    pub fov_deg: f64,
    pub pitch_deg: f64,
}

/// One view of one (possibly blended) shape and appearance: what `/api/render` and the
/// exports draw.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    pub shape: SourceSpec,
    pub shape_blend: Option<(SourceSpec, f64)>,
    pub appearance: SourceSpec,
    pub appearance_blend: Option<(SourceSpec, f64)>,
    /// Degrees: yaw about the vertical axis, pitch from the +y axis, field of view.
    pub yaw: f64,
    pub pitch: f64,
    pub fov: f64,
    pub resolution: i64,
    pub samples: i64,
    pub psi: f64,
}

impl View {
    pub fn parse(q: &Query, l: &Limits) -> Result<Self, ApiError> {
        let shape = q.source("shape", None)?;
        let appearance = q.source("appearance", Some(shape.clone()))?;
        Ok(Self {
            shape_blend: q.blend("shape")?,
            appearance_blend: q.blend("appearance")?,
            shape,
            appearance,
            yaw: q.number("yaw", 0.0, (-1e6, 1e6), "degrees")?,
            pitch: q.number("pitch", l.pitch_deg, (0.0, 180.0), "degrees from the +y axis")?,
            fov: q.number("fov", l.fov_deg, (5.0, 120.0), "degrees")?,
            resolution: q.integer("res", l.default_resolution, (8, l.max_resolution), "pixels")?,
            samples: q.integer("samples", l.default_samples, (2, l.max_samples), "samples per ray")?,
            psi: q.number("psi", 1.0, (0.0, 2.0), "a truncation ψ")?,
        })
    }

    /// What the shape side depends on: the same key, the same density everywhere.
    pub fn shape_key(&self) -> String {
        let blend = self.shape_blend.as_ref().map(|(s, t)| format!("→{s}@{t}")).unwrap_or_default();
        format!("{}{blend} ψ{}", self.shape, self.psi)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> Limits {
        Limits {
            max_resolution: 128,
            max_samples: 48,
            default_resolution: 32,
            default_samples: 12,
            fov_deg: 50.0,
            pitch_deg: 61.0,
        }
    }

    #[test]
    fn a_view_reads_its_parameters_with_defaults() {
        let q =
            Query::parse("/api/render?shape=seed%3A3&appearance=features:a-1.safetensors&yaw=-30.5&res=64").unwrap();
        let v = View::parse(&q, &limits()).unwrap();
        assert_eq!(v.shape, SourceSpec::Seed(3));
        assert_eq!(v.appearance, SourceSpec::Features("a-1.safetensors".into()));
        assert_eq!((v.yaw, v.pitch, v.fov, v.resolution, v.samples, v.psi), (-30.5, 61.0, 50.0, 64, 12, 1.0));
        assert_eq!(v.shape_blend, None);
        let q = Query::parse("/x?shape=seed:1&shape_b=photo:7&shape_t=0.25").unwrap();
        let v = View::parse(&q, &limits()).unwrap();
        assert_eq!(v.appearance, SourceSpec::Seed(1), "the appearance defaults to the shape's source");
        assert_eq!(v.shape_blend, Some((SourceSpec::Photo(7), 0.25)));
    }

    /// Each bad value is refused with a message that names its parameter and the value.
    #[test]
    fn bad_values_name_their_parameter() {
        for (query, names) in [
            ("shape=seed:-1", "shape 'seed:-1'"),
            ("shape=seed:x", "shape 'seed:x'"),
            ("shape=mesh:3", "shape 'mesh:3'"),
            ("shape=features:../../etc/passwd", "shape 'features:../../etc/passwd'"),
            ("shape=features:.hidden", "shape 'features:.hidden'"),
            ("shape=features:a/b.safetensors", "shape 'features:a/b.safetensors'"),
            ("shape=seed:1&appearance=photo:abc", "appearance 'photo:abc'"),
            ("shape=seed:1&yaw=left", "yaw 'left'"),
            ("shape=seed:1&yaw=NaN", "yaw 'NaN'"),
            ("shape=seed:1&pitch=200", "pitch '200'"),
            ("shape=seed:1&res=129", "res '129'"),
            ("shape=seed:1&res=4", "res '4'"),
            ("shape=seed:1&samples=1000", "samples '1000'"),
            ("shape=seed:1&psi=-1", "psi '-1'"),
            ("shape=seed:1&shape_b=seed:2&shape_t=2", "shape_t '2'"),
            ("shape=seed:1&appearance_b=seed:-2", "appearance_b 'seed:-2'"),
            ("yaw=10", "shape: missing"),
            ("shape=seed%ZZ1", "bad percent escape"),
        ] {
            let e = Query::parse(&format!("/api/render?{query}"))
                .and_then(|q| View::parse(&q, &limits()))
                .expect_err(query);
            assert_eq!(e.status, 400, "{query}");
            assert!(e.message.contains(names), "{query}: {}", e.message);
        }
    }

    #[test]
    fn shape_keys_ignore_the_appearance_and_the_view() {
        let v = |q: &str| View::parse(&Query::parse(q).unwrap(), &limits()).unwrap();
        let a = v("/r?shape=seed:1&appearance=seed:2&yaw=10");
        let b = v("/r?shape=seed:1&appearance=seed:5&yaw=80&res=64");
        assert_eq!(a.shape_key(), b.shape_key());
        assert_ne!(a.shape_key(), v("/r?shape=seed:1&psi=0.7").shape_key());
        assert_ne!(a.shape_key(), v("/r?shape=seed:1&shape_b=seed:2&shape_t=0.5").shape_key());
    }
}
