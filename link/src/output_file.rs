//! Writing results so that a failure leaves nothing behind: every output is first written to
//! a hidden temporary file beside its destination, and only renamed into place once all the
//! outputs of a command are complete.

use std::path::{Path, PathBuf};

/// Outputs of one command, staged beside their destinations until [`Staged::commit`].
/// Dropping it without committing removes the temporaries.
#[derive(Debug, Default)]
pub struct Staged {
    files: Vec<(PathBuf, PathBuf)>,
}

/// Why an output could not be written.
#[derive(Debug, thiserror::Error)]
#[error("{}: cannot write: {source}", path.display())]
pub struct OutputError {
    path: PathBuf,
    source: std::io::Error,
}

impl Staged {
    /// Nothing staged yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// The temporary path for `destination`: hidden, in the same directory (so the final
    /// rename stays on one file system), keeping the extension (plotters picks the image
    /// format from it).
    pub fn temporary_for(&mut self, destination: &Path) -> PathBuf {
        let name = destination
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "output".into());
        let temp = destination.with_file_name(format!(".{}.partial-{name}", std::process::id()));
        self.files.push((temp.clone(), destination.to_path_buf()));
        temp
    }

    /// Stages `bytes` for `destination`.
    pub fn write(&mut self, destination: &Path, bytes: &[u8]) -> Result<(), OutputError> {
        let temp = self.temporary_for(destination);
        std::fs::write(&temp, bytes).map_err(|source| OutputError {
            path: destination.to_path_buf(),
            source,
        })
    }

    /// Moves every staged file into place.
    pub fn commit(mut self) -> Result<(), OutputError> {
        let files = std::mem::take(&mut self.files);
        for (i, (temp, dest)) in files.iter().enumerate() {
            if let Err(source) = std::fs::rename(temp, dest) {
                for (t, _) in &files[i..] {
                    let _ = std::fs::remove_file(t);
                }
                return Err(OutputError {
                    path: dest.clone(),
                    source,
                });
            }
        }
        Ok(())
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        for (temp, _) in &self.files {
            let _ = std::fs::remove_file(temp);
        }
    }
}

/// CSV `t,u,x` (shortest round-trip formatting of each number), written by the `csv` crate.
pub fn csv_t_u_x(t: &[f64], u: &[f64], x: &[f64]) -> Result<Vec<u8>, csv::Error> {
    csv_bytes(|w| {
        w.write_record(["t", "u", "x"])?;
        for ((t, u), x) in t.iter().zip(u).zip(x) {
            w.write_record([t.to_string(), u.to_string(), x.to_string()])?;
        }
        Ok(())
    })
}

/// The bytes `write` writes through a [`csv::Writer`] (quoting, delimiters and line ends are
/// the crate's).
pub fn csv_bytes(
    write: impl FnOnce(&mut csv::Writer<Vec<u8>>) -> Result<(), csv::Error>,
) -> Result<Vec<u8>, csv::Error> {
    let mut w = csv::Writer::from_writer(Vec::new());
    write(&mut w)?;
    w.into_inner().map_err(|e| e.into_error().into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nothing_appears_unless_committed() {
        let dir = tempfile::tempdir().unwrap();
        let a = dir.path().join("a.csv");
        {
            let mut s = Staged::new();
            s.write(&a, b"1").unwrap();
        }
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        let mut s = Staged::new();
        s.write(&a, b"1").unwrap();
        s.commit().unwrap();
        assert_eq!(std::fs::read(&a).unwrap(), b"1");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn csv_t_u_x_writes_a_header_and_one_row_per_sample() {
        let text = csv_t_u_x(&[0.0, 1e-5], &[1.5, -2.0], &[0.25, 3.0]).unwrap();
        assert_eq!(
            String::from_utf8(text).unwrap(),
            "t,u,x\n0,1.5,0.25\n0.00001,-2,3\n"
        );
    }
}
