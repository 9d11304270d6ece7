//! Reading the episodes format (`weights/TRAINING_FILES.md`), with typed errors for bad files.

mod common;

use common::Tensor;
use drivesim::{Episodes, Error};
use safetensors::Dtype;

/// An episodes file of `n` 4x6 frames where pixel bytes count up and action i is (i, -i).
fn file(n: usize, starts: &[i64], edit: impl FnOnce(&mut Vec<(&str, Tensor)>)) -> Vec<u8> {
    let frames = Tensor::new(Dtype::U8, vec![n, 4, 6, 3], (0..n * 72).map(|i| i as u8).collect());
    let actions: Vec<u8> = (0..n)
        .flat_map(|i| [i as f32, -(i as f32)])
        .flat_map(f32::to_le_bytes)
        .collect();
    let starts = Tensor::new(
        Dtype::I64,
        vec![starts.len()],
        starts.iter().flat_map(|s| s.to_le_bytes()).collect(),
    );
    let mut tensors = vec![
        ("frames", frames),
        ("actions", Tensor::new(Dtype::F32, vec![n, 2], actions)),
        ("episode_starts", starts),
    ];
    edit(&mut tensors);
    safetensors::serialize(tensors.iter().map(|(k, v)| (k.to_string(), v)), None).unwrap()
}

#[test]
fn episodes_split_frames_and_actions() {
    let episodes = Episodes::from_bytes(&file(5, &[0, 2], |_| {})).unwrap();
    assert_eq!((episodes.len(), episodes.frame_size()), (2, (4, 6)));
    let second = episodes.episode(1).unwrap();
    assert_eq!(second.len(), 3);
    assert_eq!(second.actions, &[2.0, -2.0, 3.0, -3.0, 4.0, -4.0]);
    let mut frame = vec![0.0; 72];
    second.frame_f32(0, &mut frame).unwrap();
    // Frame 2's first byte is 144: scaled to [-1, 1].
    assert_eq!(frame[0], 144.0 / 127.5 - 1.0);
    assert!(matches!(
        second.frame_f32(3, &mut frame),
        Err(Error::OutOfRange {
            what: "frame",
            index: 3,
            len: 3
        })
    ));
    assert!(matches!(
        episodes.episode(2),
        Err(Error::OutOfRange {
            what: "episode",
            index: 2,
            len: 2
        })
    ));
}

#[test]
fn bad_episode_files_are_rejected() {
    let err = |bytes: Vec<u8>| Episodes::from_bytes(&bytes).expect_err("bad file accepted");
    assert!(matches!(err(file(5, &[1, 2], |_| {})), Error::Episodes { .. }));
    assert!(matches!(err(file(5, &[0, 2, 2], |_| {})), Error::Episodes { .. }));
    assert!(matches!(err(file(5, &[0, 5], |_| {})), Error::Episodes { .. }));
    assert!(matches!(err(file(5, &[], |_| {})), Error::Episodes { .. }));
    let e = err(file(5, &[0], |t| {
        t[1].1 = Tensor::new(Dtype::F32, vec![5, 1], vec![0; 20])
    }));
    assert!(matches!(&e, Error::Shape { name, .. } if name == "actions"), "{e}");
    let e = err(file(5, &[0], |t| {
        t.remove(1);
    }));
    assert!(matches!(&e, Error::MissingTensor { name } if name == "actions"), "{e}");
    let e = err(file(5, &[0], |t| t[0].1.dtype = Dtype::I8));
    assert!(matches!(&e, Error::Dtype { name, .. } if name == "frames"), "{e}");
    let bytes = file(5, &[0], |_| {});
    assert!(matches!(
        Episodes::from_bytes(&bytes[..bytes.len() - 3]),
        Err(Error::Malformed { .. })
    ));
}

/// `drivesim.carracing.record` and `drivesim.comma` write `.safetensors.gz` by default.
#[test]
fn gzipped_episodes_load() {
    use flate2::{write::GzEncoder, Compression};
    use std::io::Write;
    let bytes = file(5, &[0, 2], |_| {});
    let mut gz = GzEncoder::new(Vec::new(), Compression::fast());
    gz.write_all(&bytes).unwrap();
    let gz = gz.finish().unwrap();
    let episodes = Episodes::from_bytes(&gz).unwrap();
    assert_eq!((episodes.len(), episodes.episode(1).unwrap().len()), (2, 3));
    let path = std::env::temp_dir().join(format!("drivesim-episodes-{}.safetensors.gz", std::process::id()));
    std::fs::write(&path, &gz).unwrap();
    let loaded = Episodes::load(&path);
    std::fs::remove_file(&path).unwrap();
    assert_eq!(
        loaded.unwrap().episode(0).unwrap().frames,
        episodes.episode(0).unwrap().frames
    );
    // A cut stream says what it is.
    let err = Episodes::from_bytes(&gz[..gz.len() - 9]).err().unwrap();
    assert!(
        matches!(
            err,
            Error::Malformed {
                what: "gzipped episodes file",
                ..
            }
        ),
        "{err}"
    );
}

/// Indices that would wrap when multiplied by the frame length are out of range, not frame 0.
#[test]
fn huge_frame_index_is_out_of_range() {
    let episodes = Episodes::from_bytes(&file(5, &[0], |_| {})).unwrap();
    let episode = episodes.episode(0).unwrap();
    let mut out = vec![0.0; 4 * 6 * 3];
    // 72 << 61 wraps to 0.
    for i in [5, 1 << 55, 1 << 61, usize::MAX] {
        assert!(
            matches!(
                episode.frame_f32(i, &mut out),
                Err(Error::OutOfRange {
                    what: "frame",
                    len: 5,
                    ..
                })
            ),
            "frame {i}"
        );
    }
}

/// The frame rate in an episodes file's metadata, which the trainers write into the models
/// they train; a value that is not a rate is a typed error.
#[test]
fn frame_rate_is_read_from_the_metadata() {
    let with = |metadata: Option<&str>| {
        let bytes = file(3, &[0], |_| {});
        let tensors = safetensors::SafeTensors::deserialize(&bytes).unwrap();
        let views: Vec<_> = tensors.tensors();
        let metadata = metadata.map(|hz| [("frame_hz".to_string(), hz.to_string())].into());
        Episodes::from_bytes(&safetensors::serialize(views, metadata).unwrap())
    };
    assert_eq!(with(None).unwrap().frame_hz(), None);
    assert_eq!(with(Some("12.5")).unwrap().frame_hz(), Some(12.5));
    for bad in ["0", "-4", "fast", "inf"] {
        assert!(matches!(with(Some(bad)), Err(Error::Metadata { .. })), "{bad}");
    }
}

/// DAgger's optional `labels` `[N, 2]`: read where present, sliced by episode, checked.
#[test]
fn labels_are_optional_and_checked() {
    let floats = |values: Vec<f32>| values.into_iter().flat_map(f32::to_le_bytes).collect::<Vec<u8>>();
    let labelled = |labels: Tensor| {
        move |t: &mut Vec<(&str, Tensor)>| {
            t.push(("labels", labels));
        }
    };
    let plain = Episodes::from_bytes(&file(5, &[0, 2], |_| {})).unwrap();
    assert_eq!(plain.episode(1).unwrap().labels, None);
    let good = Tensor::new(
        Dtype::F32,
        vec![5, 2],
        floats((0..10).map(|i| i as f32 * 0.5).collect()),
    );
    let episodes = Episodes::from_bytes(&file(5, &[0, 2], labelled(good))).unwrap();
    assert_eq!(
        episodes.episode(1).unwrap().labels,
        Some(&[2.0, 2.5, 3.0, 3.5, 4.0, 4.5][..])
    );
    let err =
        |labels: Tensor| Episodes::from_bytes(&file(5, &[0, 2], labelled(labels))).expect_err("bad labels accepted");
    let e = err(Tensor::new(Dtype::F32, vec![4, 2], floats(vec![0.0; 8])));
    assert!(matches!(&e, Error::Shape { name, .. } if name == "labels"), "{e}");
    let e = err(Tensor::new(Dtype::F64, vec![5, 2], vec![0; 80]));
    assert!(matches!(&e, Error::Dtype { name, .. } if name == "labels"), "{e}");
    let mut nan = vec![0.0; 10];
    nan[7] = f32::NAN;
    let e = err(Tensor::new(Dtype::F32, vec![5, 2], floats(nan)));
    assert!(e.to_string().contains("labels"), "{e}");
}

#[test]
fn rewards_are_optional_come_with_on_road_and_are_checked() {
    let rewards = |n: usize| {
        Tensor::new(
            Dtype::F32,
            vec![n],
            (0..n).flat_map(|i| (i as f32 - 1.5).to_le_bytes()).collect(),
        )
    };
    let on_road = |values: Vec<u8>| Tensor::new(Dtype::U8, vec![values.len()], values);
    let both = file(4, &[0, 3], |t| {
        t.push(("reward", rewards(4)));
        t.push(("on_road", on_road(vec![1, 0, 1, 1])));
    });
    let episodes = Episodes::from_bytes(&both).unwrap();
    let (first, second) = (episodes.episode(0).unwrap(), episodes.episode(1).unwrap());
    assert_eq!(first.rewards, Some(&[-1.5, -0.5, 0.5][..]));
    assert_eq!(first.on_road, Some(&[1, 0, 1][..]));
    assert_eq!((second.rewards, second.on_road), (Some(&[1.5][..]), Some(&[1][..])));
    let none = Episodes::from_bytes(&file(4, &[0], |_| {})).unwrap();
    assert_eq!(
        (none.episode(0).unwrap().rewards, none.episode(0).unwrap().on_road),
        (None, None)
    );
    let bad = [
        file(4, &[0], |t| t.push(("reward", rewards(4)))),
        file(4, &[0], |t| t.push(("on_road", on_road(vec![1; 4])))),
        file(4, &[0], |t| {
            t.push(("reward", rewards(3)));
            t.push(("on_road", on_road(vec![1; 4])));
        }),
        file(4, &[0], |t| {
            t.push(("reward", rewards(4)));
            t.push(("on_road", on_road(vec![1, 2, 0, 1])));
        }),
        file(4, &[0], |t| {
            t.push(("reward", rewards(4)));
            t.push(("on_road", Tensor::new(Dtype::F32, vec![4], vec![0; 16])));
        }),
    ];
    for (i, bytes) in bad.iter().enumerate() {
        let result = Episodes::from_bytes(bytes);
        assert!(matches!(result, Err(Error::Episodes { .. })), "file {i}: {result:?}");
    }
    let nan = file(2, &[0], |t| {
        t.push((
            "reward",
            Tensor::new(
                Dtype::F32,
                vec![2],
                [f32::NAN, 0.0].iter().flat_map(|v| v.to_le_bytes()).collect(),
            ),
        ));
        t.push(("on_road", on_road(vec![1, 1])));
    });
    assert!(matches!(Episodes::from_bytes(&nan), Err(Error::NonFinite { .. })));
}
