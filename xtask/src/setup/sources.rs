//! The machine's apt sources, read so that a bookworm-backports entry can reuse the mirror
//! the machine already uses (mirrors and proxies differ per site; the repository names none).
//!
//! Both formats apt reads are understood: one-line `deb [options] URI suite component...`
//! (`/etc/apt/sources.list`, `sources.list.d/*.list`) and deb822 stanzas
//! (`sources.list.d/*.sources`).

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::{Result, bail};

/// One `deb`/`deb-src` entry (a line or a stanza).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AptSource {
    pub types: Vec<String>,
    pub uris: Vec<String>,
    pub suites: Vec<String>,
    pub components: Vec<String>,
    /// `signed-by` / `Signed-By`, verbatim (a keyring path, or an inline key in deb822).
    pub signed_by: Option<String>,
    pub file: PathBuf,
    pub deb822: bool,
}

impl AptSource {
    fn is_binary_with_suite(&self, suite: &str) -> bool {
        self.types.iter().any(|t| t == "deb") && self.suites.iter().any(|s| s == suite)
    }
}

/// Parses one-line entries. Comments, blank lines and malformed lines are skipped, as apt
/// itself would reject them and they name no usable mirror.
pub fn parse_one_line(text: &str, file: &Path) -> Vec<AptSource> {
    let mut out = Vec::new();
    for line in text.lines() {
        let line = line.split('#').next().unwrap_or("").trim();
        let Some((kind, rest)) = line.split_once(char::is_whitespace) else {
            continue;
        };
        if kind != "deb" && kind != "deb-src" {
            continue;
        }
        let rest = rest.trim_start();
        let (options, rest) = match rest.strip_prefix('[') {
            Some(r) => match r.split_once(']') {
                Some((opts, after)) => (opts, after),
                None => continue,
            },
            None => ("", rest),
        };
        let mut words = rest.split_whitespace();
        let (Some(uri), Some(suite)) = (words.next(), words.next()) else {
            continue;
        };
        let signed_by = options.split_whitespace().find_map(|o| {
            o.strip_prefix("signed-by=")
                .or_else(|| o.strip_prefix("Signed-By="))
                .map(str::to_string)
        });
        out.push(AptSource {
            types: vec![kind.to_string()],
            uris: vec![uri.to_string()],
            suites: vec![suite.to_string()],
            components: words.map(str::to_string).collect(),
            signed_by,
            file: file.to_path_buf(),
            deb822: false,
        });
    }
    out
}

/// Parses deb822 stanzas (`Field: value`, continuation lines start with white space, stanzas
/// are separated by blank lines). Stanzas with `Enabled: no` are skipped.
pub fn parse_deb822(text: &str, file: &Path) -> Vec<AptSource> {
    let mut out = Vec::new();
    let mut fields: Vec<(String, String)> = Vec::new();
    let mut finish = |fields: &mut Vec<(String, String)>| {
        let get = |name: &str| {
            fields
                .iter()
                .find(|(k, _)| k.eq_ignore_ascii_case(name))
                .map(|(_, v)| v.clone())
        };
        let words = |name: &str| -> Vec<String> {
            get(name)
                .map(|v| v.split_whitespace().map(str::to_string).collect())
                .unwrap_or_default()
        };
        let enabled = get("Enabled").is_none_or(|v| !v.trim().eq_ignore_ascii_case("no"));
        let src = AptSource {
            types: words("Types"),
            uris: words("URIs"),
            suites: words("Suites"),
            components: words("Components"),
            signed_by: get("Signed-By").map(|v| v.trim().to_string()),
            file: file.to_path_buf(),
            deb822: true,
        };
        if enabled && !src.types.is_empty() && !src.uris.is_empty() && !src.suites.is_empty() {
            out.push(src);
        }
        fields.clear();
    };
    for line in text.lines() {
        if line.starts_with('#') {
            continue;
        }
        if line.trim().is_empty() {
            finish(&mut fields);
        } else if line.starts_with([' ', '\t']) {
            // Continuation of the previous field (e.g. an inline key in Signed-By).
            if let Some((_, v)) = fields.last_mut() {
                v.push('\n');
                v.push_str(line);
            }
        } else if let Some((k, v)) = line.split_once(':') {
            fields.push((k.trim().to_string(), v.trim().to_string()));
        }
    }
    finish(&mut fields);
    out
}

/// Every entry apt would read under `etc_apt` (normally `/etc/apt`), in apt's order.
pub fn read_all(etc_apt: &Path) -> Vec<AptSource> {
    let mut out = Vec::new();
    let main = etc_apt.join("sources.list");
    if let Ok(text) = fs::read_to_string(&main) {
        out.extend(parse_one_line(&text, &main));
    }
    let mut files: Vec<PathBuf> = fs::read_dir(etc_apt.join("sources.list.d"))
        .map(|d| d.flatten().map(|e| e.path()).collect())
        .unwrap_or_default();
    files.sort();
    for f in files {
        let Ok(text) = fs::read_to_string(&f) else {
            continue;
        };
        // apt ignores other extensions (e.g. `.list.disabled`), so do we.
        match f.extension().and_then(|e| e.to_str()) {
            Some("list") => out.extend(parse_one_line(&text, &f)),
            Some("sources") => out.extend(parse_deb822(&text, &f)),
            _ => {}
        }
    }
    out
}

/// What setup does about the backports suite.
#[derive(Debug, PartialEq, Eq)]
pub enum Backports {
    /// An enabled `deb` entry for the suite exists already (in this file).
    Configured(PathBuf),
    /// A new entry to write: same mirror (and keyring) as the release's own entry.
    Add(NewEntry),
}

#[derive(Debug, PartialEq, Eq)]
pub struct NewEntry {
    pub file: PathBuf,
    pub text: String,
    pub uri: String,
    /// The file of the entry whose mirror is reused.
    pub from: PathBuf,
}

/// Decides how `<release>-backports` gets configured, from the entries apt already has.
/// `sources_d` is where a new file goes (normally `/etc/apt/sources.list.d`).
pub fn plan_backports(sources: &[AptSource], release: &str, sources_d: &Path) -> Result<Backports> {
    let suite = format!("{release}-backports");
    if let Some(s) = sources.iter().find(|s| s.is_binary_with_suite(&suite)) {
        return Ok(Backports::Configured(s.file.clone()));
    }
    let Some(base) = sources.iter().find(|s| s.is_binary_with_suite(release)) else {
        bail!(
            "apt has no `deb` entry for suite `{release}` (looked in /etc/apt/sources.list and \
             /etc/apt/sources.list.d/*.list, *.sources), so there is no mirror to reuse for \
             `{suite}`; add a `{suite}` entry for your Debian mirror by hand, then re-run"
        );
    };
    // The first URI of the entry: where that stanza lists several, apt tries them in order.
    let uri = base.uris[0].clone();
    let entry = if base.deb822 {
        let mut text = format!("Types: deb\nURIs: {uri}\nSuites: {suite}\nComponents: main\n");
        if let Some(key) = &base.signed_by {
            text.push_str(&format!("Signed-By: {key}\n"));
        }
        NewEntry {
            file: sources_d.join(format!("{suite}.sources")),
            text,
            uri,
            from: base.file.clone(),
        }
    } else {
        let opts = base
            .signed_by
            .as_ref()
            .map(|k| format!("[signed-by={k}] "))
            .unwrap_or_default();
        NewEntry {
            file: sources_d.join(format!("{suite}.list")),
            text: format!("deb {opts}{uri} {suite} main\n"),
            uri,
            from: base.file.clone(),
        }
    };
    Ok(Backports::Add(entry))
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIRROR: &str = "http://mirror.example.invalid/debian";

    #[test]
    fn one_line_format_with_options_and_comments() {
        let text = format!(
            "# comment\n\
             deb [arch=amd64 signed-by=/usr/share/keyrings/k.gpg] {MIRROR} bookworm main contrib\n\
             deb-src {MIRROR} bookworm main\n\
             deb http://security.example.invalid/debian-security bookworm-security main # note\n\
             deb [broken\n\
             deb onlyuri\n"
        );
        let s = parse_one_line(&text, Path::new("/etc/apt/sources.list"));
        assert_eq!(s.len(), 3);
        assert_eq!(s[0].types, ["deb"]);
        assert_eq!(s[0].uris, [MIRROR]);
        assert_eq!(s[0].suites, ["bookworm"]);
        assert_eq!(s[0].components, ["main", "contrib"]);
        assert_eq!(s[0].signed_by.as_deref(), Some("/usr/share/keyrings/k.gpg"));
        assert_eq!(s[1].types, ["deb-src"]);
        assert_eq!(s[2].suites, ["bookworm-security"]);
        assert_eq!(s[2].components, ["main"]);
        assert!(!s[2].deb822);
    }

    #[test]
    fn deb822_format_with_disabled_stanza_and_continuation() {
        let text = format!(
            "Types: deb deb-src\n\
             # a comment inside\n\
             URIs: {MIRROR}\n\
             Suites: bookworm bookworm-updates\n\
             Components: main\n\
             Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg\n\
             \n\
             Types: deb\n\
             URIs: http://other.example.invalid/debian\n\
             Suites: bookworm-backports\n\
             Components: main\n\
             Enabled: no\n\
             \n\
             Types: deb\n\
             URIs: http://inline.example.invalid/x\n\
             Suites: stable\n\
             Signed-By:\n \
             -----BEGIN PGP PUBLIC KEY BLOCK-----\n \
             .\n \
             -----END PGP PUBLIC KEY BLOCK-----\n"
        );
        let s = parse_deb822(&text, Path::new("/etc/apt/sources.list.d/debian.sources"));
        assert_eq!(s.len(), 2, "{s:#?}");
        assert_eq!(s[0].types, ["deb", "deb-src"]);
        assert_eq!(s[0].uris, [MIRROR]);
        assert_eq!(s[0].suites, ["bookworm", "bookworm-updates"]);
        assert!(s[0].deb822);
        let key = s[1].signed_by.as_deref().unwrap();
        assert!(
            key.starts_with("-----BEGIN") && key.ends_with("\n -----END PGP PUBLIC KEY BLOCK-----"),
            "{key:?}"
        );
    }

    #[test]
    fn backports_entry_reuses_the_deb822_mirror_and_keyring() {
        let text = format!(
            "Types: deb\nURIs: {MIRROR}\nSuites: bookworm bookworm-updates\nComponents: main\n\
             Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg\n"
        );
        let src = parse_deb822(&text, Path::new("/etc/apt/sources.list.d/debian.sources"));
        let plan = plan_backports(&src, "bookworm", Path::new("/etc/apt/sources.list.d")).unwrap();
        let Backports::Add(e) = plan else {
            panic!("expected a new entry, got {plan:?}")
        };
        assert_eq!(
            e.file,
            Path::new("/etc/apt/sources.list.d/bookworm-backports.sources")
        );
        assert_eq!(
            e.text,
            format!(
                "Types: deb\nURIs: {MIRROR}\nSuites: bookworm-backports\nComponents: main\n\
                 Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg\n"
            )
        );
        assert_eq!(e.uri, MIRROR);
        assert_eq!(e.from, Path::new("/etc/apt/sources.list.d/debian.sources"));
    }

    #[test]
    fn backports_entry_reuses_the_one_line_mirror() {
        let src = parse_one_line(
            &format!("deb {MIRROR} bookworm main\n"),
            Path::new("/etc/apt/sources.list"),
        );
        let plan = plan_backports(&src, "bookworm", Path::new("/d")).unwrap();
        let Backports::Add(e) = plan else {
            panic!("expected a new entry, got {plan:?}")
        };
        assert_eq!(e.file, Path::new("/d/bookworm-backports.list"));
        assert_eq!(e.text, format!("deb {MIRROR} bookworm-backports main\n"));
    }

    #[test]
    fn existing_backports_entry_is_kept_and_missing_release_is_an_error() {
        let src = parse_one_line(
            &format!("deb {MIRROR} bookworm main\ndeb {MIRROR} bookworm-backports main\n"),
            Path::new("/etc/apt/sources.list.d/bpo.list"),
        );
        assert_eq!(
            plan_backports(&src, "bookworm", Path::new("/d")).unwrap(),
            Backports::Configured("/etc/apt/sources.list.d/bpo.list".into())
        );
        // Only a source package entry for backports does not count.
        let src = parse_one_line(
            &format!("deb-src {MIRROR} bookworm-backports main\n"),
            Path::new("/x.list"),
        );
        let err = plan_backports(&src, "bookworm", Path::new("/d"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("no `deb` entry for suite `bookworm`"), "{err}");
    }

    #[test]
    fn reads_files_apt_reads_and_ignores_others() {
        let dir = std::env::temp_dir().join(format!("xtask-apt-{}", std::process::id()));
        let d = dir.join("sources.list.d");
        fs::create_dir_all(&d).unwrap();
        fs::write(dir.join("sources.list"), format!("deb {MIRROR} bookworm main\n")).unwrap();
        fs::write(
            d.join("a.sources"),
            format!("Types: deb\nURIs: {MIRROR}\nSuites: bookworm-updates\n"),
        )
        .unwrap();
        fs::write(d.join("b.list"), format!("deb {MIRROR} bookworm-security main\n")).unwrap();
        fs::write(
            d.join("c.list.disabled"),
            format!("deb {MIRROR} bookworm-backports main\n"),
        )
        .unwrap();
        let all = read_all(&dir);
        fs::remove_dir_all(&dir).unwrap();
        let suites: Vec<&str> = all.iter().map(|s| s.suites[0].as_str()).collect();
        assert_eq!(suites, ["bookworm", "bookworm-updates", "bookworm-security"]);
    }
}
