// Just enough of UnityEngine's surface to compile bindings/csharp/FlameExample.cs (and Flame.cs
// with UNITY_5_3_OR_NEWER defined) outside Unity and drive it from FlameExampleTest.cs.
using System;
using System.Collections.Generic;

namespace UnityEngine
{
    public class Object { public string name = ""; }
    public class Component : Object
    {
        Transform own;
        /// <summary>A Transform is its own; other components are given theirs by the test.</summary>
        public Transform transform { get { return this as Transform ?? own; } set { own = value; } }
    }
    public class Behaviour : Component { }
    public class MonoBehaviour : Behaviour { }
    public class TextAsset : Object { public byte[] bytes { get { return null; } } }
    public static class Application { public static string streamingAssetsPath { get { return ""; } } }
    public static class Time { public static float time; }   // set by the test
    public struct Quaternion
    {
        public float x, y, z, w;
        public Quaternion(float x, float y, float z, float w) { this.x = x; this.y = y; this.z = z; this.w = w; }
    }
    public struct Vector3
    {
        public float x, y, z;
        public Vector3(float x, float y, float z) { this.x = x; this.y = y; this.z = z; }
    }
    public class Transform : Component
    {
        public Quaternion localRotation = new Quaternion(0, 0, 0, 1);
        public Vector3 localPosition;
        public Vector3 localScale = new Vector3(1, 1, 1);
        public Transform parent;
    }
    /// <summary>The body bones of Unity's HumanBodyBones, with Unity's values.</summary>
    public enum HumanBodyBones
    {
        Hips = 0, LeftUpperLeg = 1, RightUpperLeg = 2, LeftLowerLeg = 3, RightLowerLeg = 4, LeftFoot = 5, RightFoot = 6,
        Spine = 7, Chest = 8, Neck = 9, Head = 10, LeftShoulder = 11, RightShoulder = 12, LeftUpperArm = 13,
        RightUpperArm = 14, LeftLowerArm = 15, RightLowerArm = 16, LeftHand = 17, RightHand = 18, LeftToes = 19,
        RightToes = 20, LeftEye = 21, RightEye = 22, Jaw = 23, UpperChest = 54, LastBone = 55,
    }
    /// <summary>An Animator whose Humanoid Avatar the test fills (Bones).</summary>
    public class Animator : Behaviour
    {
        public bool isHuman = true;
        public readonly Dictionary<HumanBodyBones, Transform> Bones = new Dictionary<HumanBodyBones, Transform>();
        public Transform GetBoneTransform(HumanBodyBones bone)
        {
            Transform t;
            return Bones.TryGetValue(bone, out t) ? t : null;
        }
    }
    public static class Debug { public static void LogError(object message) { Console.Error.WriteLine("Debug.LogError: " + message); } }
    [AttributeUsage(AttributeTargets.Field)]
    public sealed class TooltipAttribute : Attribute { public TooltipAttribute(string tooltip) { } }
}

namespace AOT
{
    // In Unity this lives in UnityEngine.dll; Flame.cs defines it only outside Unity.
    [AttributeUsage(AttributeTargets.Method)]
    public sealed class MonoPInvokeCallbackAttribute : Attribute { public MonoPInvokeCallbackAttribute(Type type) { } }
}
