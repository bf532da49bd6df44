//! Fields of JSON documents (status, tuning, stream records) by dotted path, over serde_json.

use serde_json::Value;

use super::error::{Error, Result};

/// Parses `text` as JSON.
pub fn parse(text: &str) -> Result<Value> {
    serde_json::from_str(text).map_err(|source| Error::Json {
        text: text.chars().take(200).collect(),
        source,
    })
}

/// The value at a dotted path: `source.cameras.0.fps` (array elements by index).
pub fn at<'a>(v: &'a Value, path: &str) -> Option<&'a Value> {
    path.split('.').try_fold(v, |v, key| match v {
        Value::Array(a) => a.get(key.parse::<usize>().ok()?),
        _ => v.get(key),
    })
}

/// The number at a dotted path.
pub fn f64_at(v: &Value, path: &str) -> Option<f64> {
    at(v, path).and_then(Value::as_f64)
}

/// The string at a dotted path.
pub fn str_at<'a>(v: &'a Value, path: &str) -> Option<&'a str> {
    at(v, path).and_then(Value::as_str)
}

/// `[x, y, z]` at a dotted path.
pub fn vec3_at(v: &Value, path: &str) -> Option<[f64; 3]> {
    match at(v, path)?.as_array()?.as_slice() {
        [x, y, z] => Some([x.as_f64()?, y.as_f64()?, z.as_f64()?]),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dotted_paths_through_objects_and_arrays() {
        let v = parse(r#"{"source":{"cameras":[{"fps":15.5},{"fps":14}]},"p":[1,2.5,-3],"s":"x"}"#).unwrap();
        assert_eq!(f64_at(&v, "source.cameras.1.fps"), Some(14.0));
        assert_eq!(f64_at(&v, "source.cameras.2.fps"), None);
        assert_eq!(str_at(&v, "s"), Some("x"));
        assert_eq!(vec3_at(&v, "p"), Some([1.0, 2.5, -3.0]));
        assert_eq!(at(&v, "source.nope"), None);
        assert!(parse("{oops").unwrap_err().to_string().contains("not JSON"));
    }
}
