//! Expansion of the image arguments of `vernier detect`: files, folders and glob patterns.

use std::cmp::Ordering;
use std::path::{Path, PathBuf};

/// Extensions (lower case) of the image files picked from folders and globs.
pub const IMAGE_EXTENSIONS: [&str; 8] = ["png", "jpg", "jpeg", "tif", "tiff", "pgm", "pnm", "ppm"];

/// True when `path` has an image extension (case-insensitive).
fn is_image(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| IMAGE_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
}

/// Orders file names as people do: digit runs compare by value, so `Image96.png` comes
/// before `Image100.png` (frame numbers without leading zeros stay in time order).
pub fn natural_cmp(a: &str, b: &str) -> Ordering {
    let (mut a, mut b) = (a, b);
    loop {
        match (a.chars().next(), b.chars().next()) {
            (None, None) => return Ordering::Equal,
            (None, Some(_)) => return Ordering::Less,
            (Some(_), None) => return Ordering::Greater,
            (Some(x), Some(y)) if x.is_ascii_digit() && y.is_ascii_digit() => {
                let split = |s: &str| {
                    let end = s.find(|c: char| !c.is_ascii_digit()).unwrap_or(s.len());
                    (s[..end].to_string(), end)
                };
                let ((da, ea), (db, eb)) = (split(a), split(b));
                let (ta, tb) = (da.trim_start_matches('0'), db.trim_start_matches('0'));
                let order = ta
                    .len()
                    .cmp(&tb.len())
                    .then_with(|| ta.cmp(tb))
                    .then_with(|| da.len().cmp(&db.len()));
                if order != Ordering::Equal {
                    return order;
                }
                (a, b) = (&a[ea..], &b[eb..]);
            }
            (Some(x), Some(y)) => {
                if x != y {
                    return x.cmp(&y);
                }
                (a, b) = (&a[x.len_utf8()..], &b[y.len_utf8()..]);
            }
        }
    }
}

fn sort_naturally(paths: &mut [PathBuf]) {
    paths.sort_by(|a, b| natural_cmp(&a.to_string_lossy(), &b.to_string_lossy()));
}

/// True when `text` holds glob metacharacters.
fn is_glob(text: &str) -> bool {
    text.contains(['*', '?', '['])
}

/// Expands the arguments in order: a folder gives its image files (not recursive), a glob
/// pattern (`*`, `?`, `[...]`, `**` for any depth; quote it so that the shell leaves it
/// alone) its matching image files, each sorted in natural order; any other argument is
/// taken as one file, whatever its extension. A folder or pattern without image is an error.
pub fn expand_inputs(args: &[PathBuf]) -> Result<Vec<PathBuf>, String> {
    let mut out = Vec::new();
    for arg in args {
        let text = arg.to_string_lossy();
        let mut found: Vec<PathBuf> = if arg.is_dir() {
            std::fs::read_dir(arg)
                .map_err(|e| format!("{}: {e}", arg.display()))?
                .filter_map(|entry| entry.ok().map(|e| e.path()))
                .filter(|p| p.is_file() && is_image(p))
                .collect()
        } else if is_glob(&text) && !arg.exists() {
            glob::glob(&text)
                .map_err(|e| format!("bad pattern `{text}`: {e}"))?
                .filter_map(|entry| entry.ok())
                .filter(|p| p.is_file() && is_image(p))
                .collect()
        } else {
            out.push(arg.clone());
            continue;
        };
        if found.is_empty() {
            return Err(format!(
                "`{text}` holds no image file ({})",
                IMAGE_EXTENSIONS.join(", ")
            ));
        }
        sort_naturally(&mut found);
        out.append(&mut found);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn natural_order() {
        let mut names = vec![
            "Image100.png",
            "Image96.png",
            "b2",
            "a10",
            "a2",
            "a02",
            "img_1_10",
        ];
        names.sort_by(|a, b| natural_cmp(a, b));
        assert_eq!(
            names,
            [
                "Image96.png",
                "Image100.png",
                "a2",
                "a02",
                "a10",
                "b2",
                "img_1_10"
            ]
        );
    }

    #[test]
    fn folders_and_globs() {
        let dir = std::env::temp_dir().join(format!("vernier_inputs_{}", std::process::id()));
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        for name in ["f10.png", "f9.PNG", "notes.txt", "sub/f1.jpg"] {
            std::fs::write(dir.join(name), b"x").unwrap();
        }
        let folder = expand_inputs(std::slice::from_ref(&dir)).unwrap();
        assert_eq!(folder, [dir.join("f9.PNG"), dir.join("f10.png")]);
        let deep = expand_inputs(&[dir.join("**/*.jpg")]).unwrap();
        assert_eq!(deep, [dir.join("sub/f1.jpg")]);
        let plain = expand_inputs(&[dir.join("notes.txt")]).unwrap();
        assert_eq!(plain, [dir.join("notes.txt")], "explicit files are kept");
        let e = expand_inputs(&[dir.join("*.tif")]).unwrap_err();
        assert!(e.contains("no image"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
