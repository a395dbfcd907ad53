//! Expansion of the image arguments of `vernier detect`: files, folders and glob patterns.

use std::cmp::Ordering;
use std::collections::HashSet;
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
///
/// Files found in folders and by patterns are deduplicated by canonical path (a file reached
/// through a symlink, or by two patterns, is measured once), and `**` enters every directory
/// at most once, so directory symlink loops are never followed round.
pub fn expand_inputs(args: &[PathBuf]) -> Result<Vec<PathBuf>, String> {
    let mut out = Vec::new();
    let mut seen: HashSet<PathBuf> = HashSet::new();
    for arg in args {
        let text = arg.to_string_lossy();
        let found: Vec<PathBuf> = if arg.is_dir() {
            std::fs::read_dir(arg)
                .map_err(|e| format!("{}: {e}", arg.display()))?
                .filter_map(|entry| entry.ok().map(|e| e.path()))
                .filter(|p| p.is_file() && is_image(p))
                .collect()
        } else if is_glob(&text) && !arg.exists() {
            glob_files(&text)?
                .into_iter()
                .filter(|p| is_image(p))
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
        let mut found: Vec<PathBuf> = found
            .into_iter()
            .filter(|p| seen.insert(std::fs::canonicalize(p).unwrap_or_else(|_| p.clone())))
            .collect();
        sort_naturally(&mut found);
        out.append(&mut found);
    }
    Ok(out)
}

/// One component of a glob pattern: `**` (any number of directories) or a name pattern.
enum GlobPart {
    AnyDepth,
    Name(glob::Pattern),
}

/// The files matching a glob pattern. The literal leading directories are taken as they are;
/// each directory is read at most once per pattern component (by canonical path), so
/// symlink loops end and overlapping `**` never multiplies the work.
fn glob_files(pattern: &str) -> Result<Vec<PathBuf>, String> {
    let bad = |e: glob::PatternError| format!("bad pattern `{pattern}`: {e}");
    let mut base = PathBuf::new();
    let mut parts = Vec::new();
    for component in Path::new(pattern).components() {
        let text = component.as_os_str().to_string_lossy();
        if parts.is_empty() && !is_glob(&text) && text != "**" {
            base.push(component);
        } else if text == "**" {
            parts.push(GlobPart::AnyDepth);
        } else {
            parts.push(GlobPart::Name(glob::Pattern::new(&text).map_err(bad)?));
        }
    }
    if matches!(parts.last(), Some(GlobPart::AnyDepth)) {
        parts.push(GlobPart::Name(glob::Pattern::new("*").map_err(bad)?));
    }
    let mut walk = GlobWalk {
        parts: &parts,
        visited: HashSet::new(),
        found: Vec::new(),
    };
    walk.visit(&base, 0);
    Ok(walk.found)
}

struct GlobWalk<'a> {
    parts: &'a [GlobPart],
    /// (canonical directory, pattern component) pairs already read.
    visited: HashSet<(PathBuf, usize)>,
    found: Vec<PathBuf>,
}

impl GlobWalk<'_> {
    /// Matches `parts[index..]` below `dir` (`""` = the current directory).
    fn visit(&mut self, dir: &Path, index: usize) {
        let Some(part) = self.parts.get(index) else {
            return;
        };
        let listed = if dir.as_os_str().is_empty() {
            Path::new(".")
        } else {
            dir
        };
        let canonical = std::fs::canonicalize(listed).unwrap_or_else(|_| listed.to_path_buf());
        if !self.visited.insert((canonical, index)) {
            return;
        }
        let Ok(entries) = std::fs::read_dir(listed) else {
            return;
        };
        let mut names: Vec<std::ffi::OsString> = entries
            .filter_map(|e| e.ok().map(|e| e.file_name()))
            .collect();
        names.sort();
        match part {
            GlobPart::AnyDepth => {
                // Zero directories, then one more level.
                self.visit(dir, index + 1);
                for name in names {
                    let path = dir.join(&name);
                    if path.is_dir() {
                        self.visit(&path, index);
                    }
                }
            }
            GlobPart::Name(pattern) => {
                let last = index + 1 == self.parts.len();
                for name in names {
                    let text = name.to_string_lossy();
                    if !pattern.matches(&text) {
                        continue;
                    }
                    let path = dir.join(&name);
                    if last {
                        if path.is_file() {
                            self.found.push(path);
                        }
                    } else if path.is_dir() {
                        self.visit(&path, index + 1);
                    }
                }
            }
        }
    }
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
        let middle = expand_inputs(&[dir.join("s*/*.jpg")]).unwrap();
        assert_eq!(middle, [dir.join("sub/f1.jpg")]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[cfg(unix)]
    #[test]
    fn symlink_loops_and_duplicates_are_not_followed_round() {
        let dir = std::env::temp_dir().join(format!("vernier_loops_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("a/b")).unwrap();
        std::fs::write(dir.join("a/b/img.png"), b"x").unwrap();
        // Two loops back to the top, and a second name of the image.
        std::os::unix::fs::symlink(&dir, dir.join("a/b/up")).unwrap();
        std::os::unix::fs::symlink(dir.join("a"), dir.join("a/b/again")).unwrap();
        std::os::unix::fs::symlink(dir.join("a/b/img.png"), dir.join("a/alias.png")).unwrap();
        let found = expand_inputs(&[dir.join("**/*.png")]).unwrap();
        assert_eq!(found.len(), 1, "{found:?}");
        // Across arguments too: a folder then a pattern reaching the same file.
        let both = expand_inputs(&[dir.join("a/b"), dir.join("**/img.png")]).unwrap();
        assert_eq!(both, [dir.join("a/b/img.png")]);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
