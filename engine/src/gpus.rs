//! The GPUs a local run places its model stages on: read from the driver (`nvidia-smi`), as
//! `CUDA_VISIBLE_DEVICES` leaves them, restricted by `[pipeline] gpus` / `--gpus`, and only
//! those of the first one's model, whose numeric class the keys name (so where a stage lands
//! never changes its bytes). `RLMFLOW_GPU_INVENTORY` declares the GPUs instead of the driver:
//! how the tests give the scheduler a machine they do not have, and how the device check runs
//! stages one at a time (a GPU of undeclared memory is held whole by each).

use anyhow::bail;

/// The variable that declares the inventory: `INDEX:MODEL[:MIB]` entries, comma-separated.
pub const DECLARED: &str = "RLMFLOW_GPU_INVENTORY";

/// One GPU of this machine.
#[derive(Clone, Debug, PartialEq)]
pub struct Gpu {
    /// The driver's index (PCI bus order, as `nvidia-smi` numbers them).
    pub index: usize,
    /// `GPU-...`, where the driver tells it: what a stage's worker is shown.
    pub uuid: Option<String>,
    pub model: String,
    /// Its memory in bytes, where known.
    pub memory: Option<u64>,
}

impl Gpu {
    /// The `CUDA_VISIBLE_DEVICES` that shows a stage's worker this GPU alone, with the device
    /// order that makes an index mean the driver's.
    pub fn visible(&self) -> [(&'static str, String); 2] {
        let id = self.uuid.clone().unwrap_or_else(|| self.index.to_string());
        [("CUDA_VISIBLE_DEVICES", id), ("CUDA_DEVICE_ORDER", "PCI_BUS_ID".to_owned())]
    }

    /// `cuda:2`, as a run names where a stage ran.
    pub fn device(&self) -> String {
        format!("cuda:{}", self.index)
    }

    /// `cuda:2 (NVIDIA H100 80GB HBM3, 79.6 GiB)`.
    pub fn describe(&self) -> String {
        let memory = self.memory.map_or("memory unknown".to_owned(), |m| format!("{:.1} GiB", m as f64 / (1u64 << 30) as f64));
        format!("{} ({}, {memory})", self.device(), self.model)
    }
}

/// The GPUs a run may place stages on, and a note for each one left out.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Inventory {
    pub gpus: Vec<Gpu>,
    pub left_out: Vec<String>,
}

impl Inventory {
    /// What `doctor` and a dry run show: a line per GPU a run places stages on, and each left out.
    pub fn lines(&self) -> String {
        let mut out = match self.gpus.is_empty() {
            true => "  gpus      none: GPU stages run on the CPU\n".to_owned(),
            false => self.gpus.iter().map(|g| format!("  gpu       {}\n", g.describe())).collect(),
        };
        self.left_out.iter().for_each(|note| out += &format!("  note      {note}\n"));
        out
    }
}

/// This machine's inventory; `only`: the indices `[pipeline] gpus` or `--gpus` names.
pub fn inventory(only: Option<&[usize]>) -> anyhow::Result<Inventory> {
    let found = match std::env::var(DECLARED) {
        Ok(text) => declared(&text)?,
        Err(_) => {
            // Read once a process: a run's preflight and its scheduler both ask.
            static DRIVER: std::sync::OnceLock<Vec<Gpu>> = std::sync::OnceLock::new();
            DRIVER.get_or_init(from_driver).clone()
        }
    };
    select(found, std::env::var("CUDA_VISIBLE_DEVICES").ok().as_deref(), only)
}

/// `INDEX:MODEL[:MIB],...`; without MIB the memory is unknown.
fn declared(text: &str) -> anyhow::Result<Vec<Gpu>> {
    let entry = |item: &str| -> Option<Gpu> {
        let mut parts = item.trim().splitn(3, ':');
        let index = parts.next()?.parse().ok()?;
        let model = parts.next().filter(|m| !m.is_empty())?.to_owned();
        let memory = match parts.next() {
            Some(mib) => Some(mib.parse::<u64>().ok()? << 20),
            None => None,
        };
        Some(Gpu { index, uuid: None, model, memory })
    };
    let items = text.split(',').filter(|i| !i.trim().is_empty());
    items.map(|item| entry(item).ok_or_else(|| anyhow::anyhow!("{DECLARED}: `{item}` is not INDEX:MODEL[:MIB] (e.g. `0:H100:81559`)"))).collect()
}

/// Every GPU `nvidia-smi` lists; none without it.
fn from_driver() -> Vec<Gpu> {
    let Ok(out) = std::process::Command::new("nvidia-smi")
        .args(["--query-gpu=index,uuid,name,memory.total", "--format=csv,noheader,nounits"])
        .stderr(std::process::Stdio::null())
        .output()
    else {
        return Vec::new();
    };
    let text = String::from_utf8_lossy(&out.stdout);
    let line = |l: &str| -> Option<Gpu> {
        let fields: Vec<&str> = l.split(',').map(str::trim).collect();
        let [index, uuid, model, mib] = fields[..] else { return None };
        Some(Gpu { index: index.parse().ok()?, uuid: Some(uuid.to_owned()), model: model.to_owned(), memory: mib.parse::<u64>().ok().map(|m| m << 20) })
    };
    if out.status.success() { text.lines().filter_map(line).collect() } else { Vec::new() }
}

/// `found` as `CUDA_VISIBLE_DEVICES` (`visible`) shows it and `only` restricts it, of the
/// first one's model.
fn select(found: Vec<Gpu>, visible: Option<&str>, only: Option<&[usize]>) -> anyhow::Result<Inventory> {
    let mut gpus = match visible {
        None => found,
        // As CUDA reads it: indices or UUIDs, up to the first entry that is neither.
        Some(list) => {
            let mut shown = Vec::new();
            for id in list.split(',').map(str::trim) {
                let Some(gpu) = found.iter().find(|g| g.index.to_string() == id || g.uuid.as_deref().is_some_and(|u| u.starts_with(id) && id.len() > 4)) else {
                    break;
                };
                shown.push(gpu.clone());
            }
            shown
        }
    };
    if let Some(only) = only {
        if let Some(missing) = only.iter().find(|n| !gpus.iter().any(|g| g.index == **n)) {
            let there: Vec<String> = gpus.iter().map(|g| g.index.to_string()).collect();
            let there = if there.is_empty() { "none".to_owned() } else { there.join(", ") };
            bail!("gpus: there is no GPU {missing} here (this machine's, as CUDA_VISIBLE_DEVICES shows them: {there})");
        }
        gpus.retain(|g| only.contains(&g.index));
    }
    let mut left_out = Vec::new();
    if let Some(model) = gpus.first().map(|g| g.model.clone()) {
        for g in gpus.iter().filter(|g| g.model != model) {
            left_out.push(format!("{} is left out: the keys name the class of {model}, and another model may compute other bytes", g.describe()));
        }
        gpus.retain(|g| g.model == model);
    }
    Ok(Inventory { gpus, left_out })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_inventory_is_what_cuda_shows_restricted_and_of_one_model() {
        let found = declared("0:H100:81559, 1:H100:81559, 2:H100:81559, 3:A100:40960").unwrap();
        assert_eq!(found[1], Gpu { index: 1, uuid: None, model: "H100".into(), memory: Some(81559 << 20) });
        let indices = |inv: &Inventory| inv.gpus.iter().map(|g| g.index).collect::<Vec<_>>();
        let all = select(found.clone(), None, None).unwrap();
        assert_eq!(indices(&all), [0, 1, 2]);
        assert!(all.left_out[0].starts_with("cuda:3 (A100, 40.0 GiB) is left out"), "{:?}", all.left_out);
        assert_eq!(indices(&select(found.clone(), Some("2,0"), None).unwrap()), [2, 0], "in CUDA's order");
        assert_eq!(indices(&select(found.clone(), Some("1,none,2"), None).unwrap()), [1], "up to the first that is not a device");
        assert_eq!(indices(&select(found.clone(), Some(""), None).unwrap()), Vec::<usize>::new());
        assert_eq!(indices(&select(found.clone(), None, Some(&[2, 1])).unwrap()), [1, 2]);
        let e = select(found.clone(), Some("0,1"), Some(&[2])).unwrap_err().to_string();
        assert_eq!(e, "gpus: there is no GPU 2 here (this machine's, as CUDA_VISIBLE_DEVICES shows them: 0, 1)");
        assert_eq!(declared("0:H100").unwrap()[0].memory, None, "memory undeclared: unknown");
        assert!(declared("0:H100:80G").unwrap_err().to_string().contains("`0:H100:80G` is not INDEX:MODEL[:MIB]"));
        assert!(declared("x:H100").is_err() && declared("0").is_err());
        let uuid = Gpu { uuid: Some("GPU-4f2a".into()), ..found[0].clone() };
        assert_eq!(uuid.visible()[0], ("CUDA_VISIBLE_DEVICES", "GPU-4f2a".to_owned()));
        assert_eq!(found[2].visible(), [("CUDA_VISIBLE_DEVICES", "2".to_owned()), ("CUDA_DEVICE_ORDER", "PCI_BUS_ID".to_owned())]);
    }
}
