// A Unity example of the libflame bindings: generates a motion on a worker thread and hands the
// latest pose buffer to the main thread. Put Flame.cs and this file under Assets/, the native
// library under Assets/Plugins/ (see bindings/csharp/README.md), the model under
// Assets/StreamingAssets/ (or assign it as a TextAsset renamed to .bytes).
//
// Why it is shaped like this:
// - The main thread never waits for libflame: loading and every step run on the worker.
// - A FlameSession is used by one thread at a time, so the worker also reads the poses (between
//   its steps) and publishes a copy under a lock; Update only copies that buffer.
// - Native statics survive domain reloads (entering play mode again keeps the library loaded):
//   libflame keeps no global state to reset, and everything this component creates is freed in
//   OnDestroy. Rebuilding the native library needs an Editor restart to be picked up.
#if UNITY_5_3_OR_NEWER
using System;
using System.IO;
using System.Threading;
using UnityEngine;

namespace Flame
{
    public class FlameExample : MonoBehaviour
    {
        [Tooltip("Model file under StreamingAssets (ignored when Model Asset is set).")]
        public string modelFile = "flame_tiny.safetensors";
        [Tooltip("The model as a TextAsset (a copy named *.bytes); needed where StreamingAssets is not a folder (Android).")]
        public TextAsset modelAsset;
        public string prompt = "a person walks forward and waves.";
        public int frames = 120;
        public int steps = 50;
        public FlameSampler sampler = FlameSampler.Ddim;
        public float guidance = -1f;   // negative: the model's default
        public long seed = 1;
        [Tooltip("Worker threads of the session; 0 = one per core. Leave some for the game.")]
        public int threads = 2;
        [Tooltip("Show the clean-motion estimate while stepping (a preview), not the noisy sample.")]
        public bool previewEstimate = true;

        /// <summary>Steps done and total, for a progress bar (written by the worker).</summary>
        public int StepsDone { get { return Volatile.Read(ref stepsDone); } }
        public int StepsTotal { get { return Volatile.Read(ref stepsTotal); } }
        /// <summary>The last error on the worker, if any (read on the main thread).</summary>
        public string Error { get; private set; }
        /// <summary>The latest features, frames × FeatureDim, copied in Update; null until the first step.</summary>
        public float[] Pose { get; private set; }
        public int FeatureDim { get; private set; }

        // The handles are created on the worker and freed in OnDestroy; handlesLock makes sure a
        // worker still loading when the component is destroyed frees what it creates itself.
        readonly object handlesLock = new object();
        FlameModel model;        // guarded by handlesLock
        FlameSession session;    // guarded by handlesLock
        bool stopping;           // guarded by handlesLock
        Thread worker;
        int stepsDone, stepsTotal;

        readonly object latestLock = new object();
        float[] latest;          // the worker's newest buffer, guarded by latestLock
        bool latestIsNew;        // guarded by latestLock
        string workerError;      // guarded by latestLock

        void Start()
        {
            // Unity objects only on the main thread: resolve the path / copy the bytes here.
            byte[] bytes = modelAsset != null ? modelAsset.bytes : null;
            string path = Path.Combine(Application.streamingAssetsPath, modelFile);
            worker = new Thread(() => Generate(path, bytes)) { IsBackground = true, Name = "flame" };
            worker.Start();
        }

        void Generate(string path, byte[] bytes)
        {
            try
            {
                var m = bytes != null ? FlameModel.LoadFromMemory(bytes) : FlameModel.Load(path);
                var p = FlameSessionParams.Default();
                p.frames = (uint)frames;
                p.steps = (uint)steps;
                p.sampler = (int)sampler;
                p.guidance = guidance;
                p.seed = (ulong)seed;
                p.threads = (uint)threads;
                var s = m.NewSession(p);
                lock (handlesLock)
                {
                    if (stopping)
                    {
                        s.Dispose();
                        m.Dispose();
                        return;
                    }
                    model = m;
                    session = s;
                }
                FeatureDim = m.Info.FeatureDim;
                s.SetProgressCallback((done, total) =>
                {
                    Volatile.Write(ref stepsDone, done);
                    Volatile.Write(ref stepsTotal, total);
                });
                s.SetPrompt(prompt);

                var buffer = new float[s.Frames * FeatureDim];
                int left = s.StepsLeft;
                while (left > 0)
                {
                    // OnDestroy cancels the running step; this catches a destroy between steps.
                    lock (handlesLock)
                        if (stopping)
                            return;
                    left = s.Step();
                    var which = previewEstimate && left > 0 ? FlameWhich.Estimate : FlameWhich.Sample;
                    s.ReadInto(buffer, which, FlameLayout.Features, FlameConvention.Native, 0);
                    lock (latestLock)
                    {
                        // Swap instead of copying: the worker gets the old buffer back to fill.
                        var published = buffer;
                        buffer = latest ?? new float[published.Length];
                        latest = published;
                        latestIsNew = true;
                    }
                }
            }
            catch (FlameException e)
            {
                if (e.Status != FlameStatus.Cancelled)
                    lock (latestLock) workerError = e.Message;
            }
            catch (ObjectDisposedException)
            {
                // OnDestroy disposed the session while this thread was finishing: nothing to do.
            }
            catch (Exception e)
            {
                lock (latestLock) workerError = e.ToString();
            }
        }

        void Update()
        {
            lock (latestLock)
            {
                if (workerError != null)
                {
                    Error = workerError;
                    workerError = null;
                    Debug.LogError("libflame: " + Error);
                }
                if (!latestIsNew)
                    return;
                if (Pose == null || Pose.Length != latest.Length)
                    Pose = new float[latest.Length];
                Array.Copy(latest, Pose, latest.Length);
                latestIsNew = false;
            }
            // Pose now holds frames × FeatureDim features for this frame's use (e.g. play back frame
            // (int)(Time.time * model.Info.Fps) % frames). Joint rotations in a Unity convention
            // will come from a pose layout / convention in Read, instead of FlameLayout.Features.
        }

        void OnDestroy()
        {
            FlameModel m;
            FlameSession s;
            lock (handlesLock)
            {
                stopping = true;
                m = model;
                s = session;
                model = null;
                session = null;
            }
            if (s != null)
                s.Cancel();
            // Cancel makes a running step return soon; still, never hang the main thread on it:
            // disposing while a step runs is safe (the SafeHandle defers the free until it returns).
            if (worker != null)
                worker.Join(500);
            if (s != null)
                s.Dispose();
            if (m != null)
                m.Dispose();
        }
    }
}
#endif
